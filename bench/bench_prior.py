"""Issue 57 item 3: does an operator's prior (Nav2's /initialpose) shorten the time to localize where the building is
ambiguous, and does a wrong one ever make a wrong `localized`?

    python -m bench.bench_prior [--seeds 0,1,2,3] [--storeys "Level 1,Level 2"] [--duration 40]

Ground-truth flights (sim.truth_flight) through the duplex (data/buildings/duplex.ifc: two mirrored flats, the
model half-turn symmetric), replayed three times each as the service runs them (service.offline.run.replay_flight,
the default config): no prior; the right prior (the true pose at the first frame, sigma 0.5 m / 15 deg, as rviz's 2D
Pose Estimate sends); a wrong one (the true pose moved 10 m sideways and onto the other storey). The vehicle sends
the prior on `initialpose` after the first frame, as an operator would after take-off (graph.prior: it picks among
poses the registration leaves tied, nothing else).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DUPLEX = ROOT / "data/buildings/duplex.ifc"


def _pose_estimate(T_cad_body: np.ndarray, stamp_ns: int, storey: str = ""):  # noqa: ANN202 - pb.PoseEstimate
    """The operator's prior as on `initialpose` (frame cad; no covariance: rviz's sigmas, service.inputs)."""
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.proto.recording import pose_from_matrix

    m = pb.PoseEstimate(storey=storey, T_cad_body=pose_from_matrix(T_cad_body))
    m.header.frame_id, m.header.stamp_ns = "cad", stamp_ns
    return m


def main() -> None:
    from macroloc.graph.bim import load_building
    from macroloc.proto.recording import matrix_from_pose, read_flight
    from macroloc.service.config import load_config
    from macroloc.service.offline.run import ReplayOptions, replay_flight
    from macroloc.sim.truth_flight import write_truth_flight

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0,1,2,3")
    parser.add_argument("--storeys", default="Level 1,Level 2")
    parser.add_argument("--duration", type=float, default=40.0)
    parser.add_argument("--out", type=Path, default=Path("/tmp/macroloc-flights"))
    args = parser.parse_args()
    model = load_building(DUPLEX)
    cfg = load_config(None)
    storeys = args.storeys.split(",")

    def right(T_cad_body: np.ndarray, stamp_ns: int):  # noqa: ANN202
        return _pose_estimate(T_cad_body, stamp_ns)

    def wrong_for(storey: str):  # noqa: ANN202
        other = next(s for s in storeys if s != storey) if len(storeys) > 1 else storey
        dz = model.storey_elevations_m[other] - model.storey_elevations_m[storey]

        def wrong(T_cad_body: np.ndarray, stamp_ns: int):  # noqa: ANN202
            T = T_cad_body.copy()
            T[:3, 3] += (10.0 * np.cos(0.3), 10.0 * np.sin(0.3), dz)  # 10 m sideways, on the other storey
            return _pose_estimate(T, stamp_ns, storey=other)
        return wrong

    print(f"{'storey':<8} {'seed':>4} {'prior':>6} {'taken':>5} {'localize s':>10} {'wrong':>5} {'by prior':>8} "
          f"{'final':>10}")
    args.out.mkdir(parents=True, exist_ok=True)
    for storey in storeys:
        for seed in [int(s) for s in args.seeds.split(",")]:
            flight = args.out / f"duplex-{storey.replace(' ', '')}-{int(args.duration)}s-{seed}.mcap"
            if not flight.exists():
                write_truth_flight(DUPLEX, flight, seed=seed, duration_s=args.duration, storey=storey)
            first = next(iter(read_flight(flight)))
            T_cad_body = matrix_from_pose(first.ground_truth.T_cad_body)
            for name, make_prior in (("none", None), ("right", right), ("wrong", wrong_for(storey))):
                prior = None if make_prior is None else make_prior(T_cad_body, first.stamp_ns)
                replayed = replay_flight(flight, DUPLEX, cfg, ReplayOptions(seed=seed), prior=prior)
                r = replayed.result
                j = r.to_json()
                anchoring = replayed.front_end.localizer.anchoring
                by_prior, taken = len(anchoring.by_prior), "yes" if anchoring.prior is not None else "no"
                print(f"{storey:<8} {seed:>4} {name:>6} {taken:>5} {j['time_to_localize_s']!s:>10} "
                      f"{j['wrong_localizations']:>5} {by_prior:>8} {j['status_final']:>10}", flush=True)


if __name__ == "__main__":
    main()
