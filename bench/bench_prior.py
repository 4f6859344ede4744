"""Issue 57 item 3: does an operator's prior (Nav2's /initialpose) shorten the time to localize where the building is
ambiguous, and does a wrong one ever make a wrong `localized`?

    python -m bench.bench_prior [--seeds 0,1,2,3] [--storeys "Level 1,Level 2"] [--duration 40]

Ground-truth flights (sim.truth_flight) through the duplex (data/buildings/duplex.ifc: two mirrored flats, the
model half-turn symmetric), replayed in-process three times each with the session the service runs: no prior; the
right prior (the true pose after the first frame, sigma 0.5 m / 15 deg, as rviz's 2D Pose Estimate sends); a wrong
one (the true pose moved 10 m sideways and onto the other storey). The prior is given after the first frame, as an
operator would after take-off (graph.prior: it picks among poses the registration leaves tied, nothing else).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DUPLEX = ROOT / "data/buildings/duplex.ifc"


class _PriorAtFirstFrame:
    """A replay recorder that gives the session a prior built from the first frame's truth and estimate."""

    def __init__(self, sessions: list, make_prior) -> None:  # noqa: ANN001
        self.sessions, self.make_prior, self.given = sessions, make_prior, False

    def frame(self, frame, inputs, est) -> None:  # noqa: ANN001
        from macroloc.proto.recording import matrix_from_pose

        if not self.given and frame.ground_truth is not None:
            T_cad_body = matrix_from_pose(frame.ground_truth.T_cad_body)
            self.sessions[-1].localizer.set_prior(self.make_prior(T_cad_body, est.T_map_body))
            self.given = True

    def finish(self, localizer) -> None:  # noqa: ANN001
        pass


def main() -> None:
    from macroloc.graph.bim import load_building
    from macroloc.graph.prior import PosePrior, storey_band_m
    from macroloc.service.config import load_config
    from macroloc.service.offline.replay import replay
    from macroloc.service.offline.replay_sources import TruthSource
    from macroloc.service.session import session_from_config
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

    def right(T_cad_body: np.ndarray, T_map_body: np.ndarray) -> PosePrior:
        return PosePrior(T_cad_map=T_cad_body @ np.linalg.inv(T_map_body))

    def wrong_for(storey: str):  # noqa: ANN202
        other = next(s for s in storeys if s != storey) if len(storeys) > 1 else storey
        dz = model.storey_elevations_m[other] - model.storey_elevations_m[storey]

        def wrong(T_cad_body: np.ndarray, T_map_body: np.ndarray) -> PosePrior:
            T = T_cad_body.copy()
            T[:3, 3] += (10.0 * np.cos(0.3), 10.0 * np.sin(0.3), dz)  # 10 m sideways, on the other storey
            return PosePrior(T_cad_map=T @ np.linalg.inv(T_map_body), storey=other,
                             storey_band_m=storey_band_m(model, other))
        return wrong

    print(f"{'storey':<8} {'seed':>4} {'prior':>6} {'localize s':>10} {'wrong':>5} {'by prior':>8} {'final':>10}")
    args.out.mkdir(parents=True, exist_ok=True)
    for storey in storeys:
        for seed in [int(s) for s in args.seeds.split(",")]:
            flight = args.out / f"duplex-{storey.replace(' ', '')}-{int(args.duration)}s-{seed}.mcap"
            if not flight.exists():
                write_truth_flight(DUPLEX, flight, seed=seed, duration_s=args.duration, storey=storey)
            for name, make_prior in (("none", None), ("right", right), ("wrong", wrong_for(storey))):
                sessions: list = []

                def make(T_body_cam, sessions=sessions):  # noqa: ANN001, ANN202
                    sessions.append(session_from_config(cfg, model, T_body_cam=T_body_cam))
                    return sessions[-1]

                recorder = None if make_prior is None else _PriorAtFirstFrame(sessions, make_prior)
                r = replay(flight, model, TruthSource(seed=seed), make=make, recorder=recorder)
                j = r.to_json()
                by_prior = len(r.localizer.anchoring.by_prior)
                print(f"{storey:<8} {seed:>4} {name:>6} {j['time_to_localize_s']!s:>10} "
                      f"{j['wrong_localizations']:>5} {by_prior:>8} {j['status_final']:>10}", flush=True)


if __name__ == "__main__":
    main()
