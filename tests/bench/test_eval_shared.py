"""bench/eval_shared.py: the shared harness's commands run in this process keep the CLI's contract."""

from __future__ import annotations

import json
from pathlib import Path

from bench.eval_shared import in_process_cli


def test_a_users_mistake_is_exit_2_and_one_stderr_line(tmp_path: Path) -> None:
    rc, out, err, _ = in_process_cli(["macroloc", "localize", str(tmp_path / "missing.ifc"), "--observations",
                                      str(tmp_path / "OBS.json"), "--json"])
    assert rc == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and err.startswith("macroloc: error:")


def test_an_answer_is_the_clis_json_with_the_registration_time_apart(tmp_path: Path, office_path: Path,
                                                                     office_model) -> None:
    import numpy as np

    from tests.cli.test_cli_localize import obs_doc, random_T

    obs = tmp_path / "OBS.json"
    obs.write_text(json.dumps(obs_doc(office_model, random_T(np.random.default_rng(3), yaw_only=True), "Level 2")))
    rc, out, err, _ = in_process_cli(["macroloc", "localize", str(office_path), "--observations", str(obs), "--json"])
    doc = json.loads(out)
    assert rc == 0, err
    assert doc["status"] in ("localized", "ambiguous")
    assert 0.0 < doc["elapsed_ms"] < doc["total_ms"]
