"""The flight benchmark's summary and its comparison with an earlier run (bench.bench_flights)."""

from __future__ import annotations

from bench.bench_flights import differences, summary


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
