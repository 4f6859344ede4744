"""The service's commands as a user runs them: dump-config, serve under SIGTERM, the demo (slow)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import zenoh

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from tests.service.helpers import free_port, loopback, wait_for

MACROLOC = str(Path(sys.executable).parent / "macroloc")


def test_dump_config_prints_every_section_and_honours_the_environment(tmp_path: Path) -> None:
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"service": {"vehicle": "from-file"}, "zenoh": {"mode": "client"}}))
    env = dict(os.environ, MACROLOC_ZENOH__MODE="router")
    done = subprocess.run([MACROLOC, "dump-config", "--config", str(cfg)], capture_output=True, text=True, env=env,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    doc = json.loads(done.stdout)
    assert {"localize", "camera", "zenoh", "service", "planning"} <= set(doc)
    assert doc["service"]["vehicle"] == "from-file" and doc["zenoh"]["mode"] == "router"


def test_serve_refuses_bad_input_with_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    for args in (["serve", "--config", str(bad)], ["serve", "--building", str(tmp_path / "missing.ifc")]):
        done = subprocess.run([MACROLOC, *args], capture_output=True, text=True, timeout=60)
        assert done.returncode == 2
        assert len(done.stderr.strip().splitlines()) == 1, done.stderr


def test_the_demo_runs_with_a_config_file_under_its_own_settings(tmp_path: Path) -> None:
    """`demo --config`: the file's keys reach the service (a [graph.judge] margin, a storey, a detector), the
    demo's own (building, vehicle, endpoints, observations) win over the file's; a bad file is one line, exit 2,
    before any flight."""
    from macroloc.cli.demo import DEFAULT_BUILDING, DemoParams, demo_config

    cfg = tmp_path / "c.toml"
    cfg.write_text('[service]\nvehicle = "from-file"\nperception = true\n\n[graph]\nstorey_hint = "Level 9"\n\n'
                   '[graph.judge]\nsurface_margin = 0.2\n\n[perception]\ndetector_model = "/x/d.onnx"\n')
    got = demo_config(DEFAULT_BUILDING, DemoParams(vehicle="demo", config=cfg, observations="truth"), 7447)
    assert got.graph.judge.surface_margin == 0.2 and got.graph.storey_hint == "Level 9"
    assert got.service.vehicle == "demo" and got.service.perception is False  # truth observations: no chain
    assert got.service.building == DEFAULT_BUILDING and str(got.perception.detector_model) == "/x/d.onnx"
    plain = demo_config(DEFAULT_BUILDING, DemoParams(), 7447)  # the default: through the perception chain
    assert plain.service.perception is True
    assert plain.graph.judge.surface_margin == 0.3 and plain.graph.storey_hint  # the take-off storey
    assert plain.perception.detector_model is not None  # the building's own detector
    bad = tmp_path / "bad.toml"
    bad.write_text("[graph.judge]\nsurface_margn = 0.2\n")
    done = subprocess.run([MACROLOC, "demo", "--config", str(bad)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "surface_margn" in done.stderr


def test_serve_stops_cleanly_on_sigterm_and_saves_the_map(office_path: Path, tmp_path: Path) -> None:
    from macroloc.service.assets import prepare_building
    from macroloc.service.config import load_config

    cfg = load_config(None)
    prepare_building(office_path, cfg.graph, cfg.planning)  # the session's cache, which serve reads: ready at once
    port = free_port()
    proc = subprocess.Popen([MACROLOC, "serve", "--building", str(office_path), "--vehicle", "cli",
                             "--listen", f"tcp/127.0.0.1:{port}", "--state-dir", str(tmp_path), "--log-json"],
                            stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, MACROLOC_SERVICE__PERCEPTION="false"))
    try:
        from macroloc.service.zenoh_io import session_config

        with zenoh.open(session_config(loopback(connect=[f"tcp/127.0.0.1:{port}"]))) as s:
            wait_for(lambda: any(r.ok for r in s.liveliness().get("macroloc/cli/alive", timeout=1.0)), 90.0,
                     "the service's liveliness token")
            s.put("macroloc/cli/odometry", b"garbage")  # must not kill it
            odo = pb.Odometry()
            odo.header.stamp_ns = 1
            odo.T_map_body.qw = 1.0
            s.put("macroloc/cli/odometry", odo.SerializeToString())
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr[-2000:]
    assert (tmp_path / "cli" / "map.pb").exists()
    assert json.loads((tmp_path / "cli" / "config.resolved.json").read_text())["service"]["vehicle"] == "cli"
    lines = [json.loads(line) for line in stderr.splitlines() if line.startswith("{")]
    assert any("stopped" in line["msg"] for line in lines), "structured log of the clean stop"


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_demo_localizes_and_reaches_the_goal(seed: int, tmp_path: Path) -> None:
    from macroloc.cli.demo import DemoParams, plot_flight, run_demo
    from macroloc.graph.planning import Planner

    result = run_demo(params=DemoParams(seed=seed, speedup=3.0, observations="truth"))
    assert result.localized and result.reached
    assert result.goal_error_m < 0.3 and result.path_length_m > 5.0
    planner = Planner.for_building(Path(__file__).resolve().parents[2] / "data/buildings/office_a.ifc", 0.2, 0.35, 1.4)
    assert plot_flight(result, planner, tmp_path / "flight.png").stat().st_size > 10_000


@pytest.mark.slow
def test_demo_closes_the_loop_through_perception(tmp_path: Path) -> None:
    """Rendered stereo frames -> the service's perception chain (the detector adapted to Office_A and shipped
    beside it) -> localized -> flown to the goal on the service's poses (~3.5 min on 2 cores); its recording
    (--record) replays offline."""
    from macroloc.cli.demo import DEFAULT_BUILDING, DemoParams, bundled_detector, run_demo

    recording = tmp_path / "demo.mcap"
    result = run_demo(params=DemoParams(seed=0, observations="perception", record=recording))
    assert "office_a_detector" in result.observations
    assert result.localized and result.reached
    assert result.goal_error_m < 0.5 and result.path_length_m > 5.0
    # the recorded flight runs again offline, perceived frame by frame as the service did, on the vehicle's odometry
    config = tmp_path / "every_frame.toml"
    config.write_text(f'[perception]\ndetect_every = 1\ndetector_model = "{bundled_detector(DEFAULT_BUILDING)}"\n')
    proc = subprocess.run([sys.executable, "-m", "macroloc.cli.main", "replay", str(recording), "--building",
                           str(DEFAULT_BUILDING), "--observations", "perception", "--config", str(config), "--json"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    replayed = json.loads(proc.stdout)
    assert replayed["localized"] and replayed["wrong_localizations"] == 0


@pytest.mark.slow
def test_killed_mid_flight_restarts_and_relocalizes(office_path: Path, office_model, tmp_path: Path) -> None:
    """SIGKILL (no chance to save at exit): the periodically saved map is intact and the restart re-localizes
    from a couple of doors, with the vehicle's odometry going on as if nothing happened."""
    import numpy as np

    from tests.service.helpers import FakeFlight, yaw_T
    from tests.service.test_service import Collector, fly

    port = free_port()
    env = dict(os.environ, MACROLOC_SERVICE__SAVE_PERIOD_S="0.3", MACROLOC_SERVICE__PERCEPTION="false")
    args = [MACROLOC, "serve", "--building", str(office_path), "--vehicle", "t1", "--listen",
            f"tcp/127.0.0.1:{port}", "--state-dir", str(tmp_path)]
    door = [f for f in office_model.features if f.type == "door" and f.storey == "Level 1"][10]
    T = yaw_T(0.3, door.centroid_cad + np.r_[door.normal_cad[:2] * 1.5, 0.4])
    flight = FakeFlight(office_model, yaw_T(2.0, np.array([5.0, -3.0, 0.0])))
    from macroloc.service.zenoh_io import session_config

    def localized(poses: Collector) -> bool:
        last = poses.last()
        return last is not None and last.status == pb.PoseEstimate.LOCALIZED

    proc = subprocess.Popen(args, env=env, stderr=subprocess.DEVNULL)
    try:
        with zenoh.open(session_config(loopback(connect=[f"tcp/127.0.0.1:{port}"]))) as s:
            wait_for(lambda: any(r.ok for r in s.liveliness().get("macroloc/t1/alive", timeout=1.0)), 90.0, "up")
            poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
            T = fly(s, flight, T, 40)
            wait_for(lambda: localized(poses), 30.0, "localized before the kill")
            saved = tmp_path / "t1" / "map.pb"
            wait_for(lambda: saved.exists() and pb.MapSnapshot.FromString(saved.read_bytes()).status
                     == pb.PoseEstimate.LOCALIZED, 30.0, "a saved localized map")
        proc.kill()
        proc.wait(30)
        proc = subprocess.Popen(args, env=env, stderr=subprocess.DEVNULL)
        flight.range_m = 2.5
        with zenoh.open(session_config(loopback(connect=[f"tcp/127.0.0.1:{port}"]))) as s:
            wait_for(lambda: any(r.ok for r in s.liveliness().get("macroloc/t1/alive", timeout=1.0)), 90.0, "up")
            poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
            fly(s, flight, T, 12, first_stamp_ns=10**10, observe_every=1)  # 0.4 s: past a keyframe interval
            wait_for(lambda: localized(poses), 30.0, "re-localized after the restart")
    finally:
        proc.kill()
        proc.wait(30)


def _busy(stop: threading.Event) -> None:
    while not stop.is_set():
        sum(i * i for i in range(10_000))  # holds the GIL and a core: the service and the vehicle get less


def test_lockstep_flies_the_same_flight_on_an_idle_and_a_loaded_machine() -> None:
    """The vehicle's clock waits for the service: 5 simulated seconds of seed 1 (localized at 2.6 s) give the same
    flight to the digit, once as it is and once with a busy thread beside it."""
    from macroloc.cli.demo import DemoParams, run_demo

    params = DemoParams(seed=1, timeout_s=5.0, lockstep=True, observations="truth")
    first = run_demo(params=params)
    stop = threading.Event()
    load = threading.Thread(target=_busy, args=(stop,), daemon=True)
    load.start()
    try:
        second = run_demo(params=params)
    finally:
        stop.set()
        load.join()
    assert len(first.true_xy) == len(second.true_xy) > 100
    assert first.localized and len(first.estimated_xy) > 50  # the estimates compared are the localized ones
    assert first.true_xy == second.true_xy and first.estimated_xy == second.estimated_xy
    assert first.localization_time_s == second.localization_time_s


@pytest.mark.slow
@pytest.mark.parametrize(("observations", "seed"), [("truth", 0), ("truth", 1), ("truth", 2), ("perception", 0)])
def test_lockstep_demo_repeats_to_the_digit(observations: str, seed: int) -> None:
    from dataclasses import asdict

    from macroloc.cli.demo import DemoParams, run_demo

    runs = [asdict(run_demo(params=DemoParams(seed=seed, lockstep=True, observations=observations)))
            for _ in range(2)]
    for run in runs:
        run.pop("wall_time_s")
    assert runs[0] == runs[1]
    assert runs[0]["localized"] and runs[0]["reached"] and not runs[0]["wall_contacts_xy"]
