"""The flight benchmark's summary, its comparison with an earlier run and of the two transports, and one run
through the library on a tiny rendered flight (bench.bench_flights)."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

from bench.bench_flights import (
    COMPARED,
    COMPARED_TRANSPORTS,
    Run,
    differences,
    replay_run,
    summary,
    transport_differences,
)


def result(t: float | None, ape: float | None, wrong: int = 0, status: str = "localized") -> dict:
    return {"localized": t is not None, "time_to_localize_s": t, "ape_rmse_m": ape, "ape_max_m": ape,
            "wrong_localizations": wrong, "status_final": status}


def test_the_summary_counts_the_runs_within_the_targets_per_observation_kind() -> None:
    runs = {"office_a s1 truth noise 0": result(5.23, 0.072), "office_a s2 truth noise 0": result(3.0, 0.062),
            "jasmin s1 truth noise 0": result(None, None, status="ambiguous"),
            "office_a s1 perception noise 0": result(4.1, 0.076, wrong=1)}
    perception, truth = summary(runs)
    assert truth.startswith("truth") and "localized 2 of 3" in truth and "<= 5 s on 1 of 3" in truth
    assert "0.062-0.072 m" in truth and "wrong 0" in truth
    assert "localized 1 of 1" in perception and "wrong 1" in perception


def test_the_comparison_lists_only_the_runs_whose_figures_moved() -> None:
    before = {"a s1 truth noise 0": result(5.23, 0.072), "a s2 truth noise 0": result(3.0, 0.062),
              "a s3 truth noise 0": result(8.67, 0.053)}
    after = {"a s1 truth noise 0": result(5.23, 0.072), "a s2 truth noise 0": result(3.0, 0.071),
             "a s4 truth noise 0": result(1.47, 0.055)}
    assert differences(before, after) == ["a s2 truth noise 0: ape_rmse_m 0.062 -> 0.071, ape_max_m 0.062 -> 0.071"]
    assert differences(before, before) == []


def test_runs_over_zenoh_have_their_own_summary_line_and_are_compared_with_the_offline_ones() -> None:
    runs = {"a s1 perception noise 0": result(16.5667, 0.076) | {"keyframes": 30},  # the offline time to 0.1 ms
            "a s1 perception noise 0 over-zenoh": result(16.567, 0.076) | {"keyframes": 30},  # the service's to 1 ms
            "a s2 perception noise 0": result(3.0, 0.05) | {"keyframes": 20},
            "a s2 perception noise 0 over-zenoh": result(3.0, 0.05) | {"keyframes": 21}}
    offline, served = summary(runs)
    assert offline.startswith("perception localized 2 of 2") and served.startswith("perception over-zenoh")
    assert transport_differences(runs) == ["a s2 perception noise 0: keyframes 20 -> 21"]
    runs["a s1 perception noise 0 over-zenoh"]["time_to_localize_s"] = 16.6
    assert transport_differences(runs)[0] == "a s1 perception noise 0: time_to_localize_s 16.5667 -> 16.6"


def test_a_run_is_a_library_call_on_the_flight(tmp_path: Path) -> None:
    """A 3 s flight (too short to localize: its first doors come in range at 5.5 s) through the service's path
    offline: every recorded frame replayed and keyframes made, with the figures the benchmark reads; a config that
    is not there is that run's error, not the benchmark's end."""
    from macroloc.cli.main import main
    from macroloc.proto.recording import stereo_frame_count

    flight = tmp_path / "office.mcap"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["simulate", str(Path(__file__).parents[2] / "data/buildings/office_a.ifc"), "--out",
                     str(flight), "--duration", "3", "--seed", "1", "--json"]) == 0
    done = replay_run(Run("office_a", 1, "truth", 0), flight)
    assert "error" not in done, done
    assert done["frames"] == stereo_frame_count(flight) > 80
    assert done["keyframes"] > 0 and done["status_final"] == "exploring" and not done["localized"]
    assert set(COMPARED) | set(COMPARED_TRANSPORTS) <= set(done)
    missing = replay_run(Run("office_a", 1, "truth", 0), flight, config=tmp_path / "absent.toml")
    assert "absent.toml" in missing["error"]
