"""The command-line contract of `features`, `localize` and `eval` (DESIGN.md), in-process and as a subprocess."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from macroloc.cli.main import main
from tests.graph.helpers import random_T


def run(args: list[str], capsys) -> tuple[int, str, str]:
    rc = main(args)
    out = capsys.readouterr()
    return rc, out.out, out.err


def obs_doc(model, T_map_cad: np.ndarray, storey: str, n: int = 12) -> dict:
    feats = [f for f in model.features if f.storey == storey][:n]
    R, t = T_map_cad[:3, :3], T_map_cad[:3, 3]
    return {"frame": "map", "gravity": (R @ [0, 0, -1.0]).tolist(),
            "features": [{"type": f.type, "corners": (f.corners_cad[::-1] @ R.T + t).tolist()} for f in feats]}


def test_features_json_contract(capsys, fzk_path: Path) -> None:
    rc, out, _ = run(["features", str(fzk_path), "--json"], capsys)
    doc = json.loads(out)
    assert rc == 0 and doc["unit"] == "m" and len(doc["features"]) == 16
    f = doc["features"][0]
    assert set(f) >= {"id", "type", "storey", "centroid", "corners", "normal"}
    assert np.array(f["corners"]).shape == (4, 3)
    geo = doc["geo"]  # FZK-Haus's IfcSite and TrueNorth (values in tests/graph/test_geo.py)
    assert geo["source"] == "IfcSite" and geo["crs"] is None
    assert abs(geo["latitude_deg"] - 49.100435) < 1e-9 and abs(geo["longitude_deg"] - 8.436539) < 1e-9
    assert abs(geo["true_north_deg"] + 50.0) < 1e-6 and geo["altitude_m"] == 110.0


def test_localize_end_to_end_on_a_real_ifc(tmp_path: Path, capsys, office_path: Path, office_model) -> None:
    T = random_T(np.random.default_rng(1), yaw_only=True)
    obs = tmp_path / "OBS.json"
    obs.write_text(json.dumps(obs_doc(office_model, T, "Level 2")))
    for method in ("robust", "paper"):
        rc, out, err = run(["localize", str(office_path), "--observations", str(obs), "--json", "--method", method],
                           capsys)
        doc = json.loads(out)
        assert rc == 0 and err == ""
        assert set(doc) >= {"status", "T_cad_map", "matches", "inliers", "storey", "elapsed_ms", "total_ms"}
        assert 0.0 < doc["elapsed_ms"] <= doc["total_ms"]  # the registration alone, inside the whole command
        if method == "robust":
            assert doc["status"] == "localized" and doc["storey"] == "Level 2"
            assert np.allclose(np.array(doc["T_cad_map"]) @ T, np.eye(4), atol=1e-4)



def test_localize_takes_the_config_files_localize_section(tmp_path: Path, capsys, office_path: Path,
                                                          office_model) -> None:
    """`[localize] min_inliers` above the observations' count turns the same answer into not_localized."""
    obs = tmp_path / "OBS.json"
    obs.write_text(json.dumps(obs_doc(office_model, random_T(np.random.default_rng(1), yaw_only=True), "Level 2",
                                      n=5)))
    config = tmp_path / "macroloc.toml"
    config.write_text("[localize]\nmin_inliers = 6\n")
    base = ["localize", str(office_path), "--observations", str(obs), "--json"]
    assert json.loads(run(base, capsys)[1])["status"] == "localized"
    assert json.loads(run([*base, "--config", str(config)], capsys)[1])["status"] == "not_localized"
def test_the_configured_registration_parameters_are_the_registrations(office_model) -> None:
    """`LocalizeConfig.robust_params()` is the robust registration's parameters, every key of the section but
    `method` among them."""
    from macroloc.graph.observations import parse_observations
    from macroloc.graph.registration import register
    from macroloc.service.config import LocalizeConfig

    T = random_T(np.random.default_rng(2), yaw_only=True)
    obs = parse_observations(obs_doc(office_model, np.linalg.inv(T), "Level 2"))
    assert register(office_model, obs, params=LocalizeConfig().robust_params()).status in ("localized", "ambiguous")
    changed = LocalizeConfig(inlier_threshold_m=0.25, landing_alpha=0.05, min_inliers=5, seed=7).robust_params()
    assert {k: getattr(changed, k) for k in ("inlier_threshold_m", "landing_alpha", "min_inliers", "seed")} == \
        dict(inlier_threshold_m=0.25, landing_alpha=0.05, min_inliers=5, seed=7)


BAD_INPUTS = {
    "missing file": None,
    "not JSON": "{not json",
    "three corners": {"frame": "map", "features": [{"type": "door", "corners": [[0, 0, 0], [1, 0, 0], [1, 0, 2]]}]},
    "NaN corner": '{"frame": "map", "features": [{"type": "door", "corners": [[NaN,0,0],[1,0,0],[1,0,2],[0,0,2]]}]}',
    "unknown type": {"frame": "map", "features": [{"type": "stairs", "centroid": [0, 0, 0]}]},
    "features not a list": {"frame": "map", "features": 3},
    "bad gravity": {"frame": "map", "gravity": [0, 0], "features": []},
    "unknown storey hint": {"frame": "map", "hints": {"storey": "Level 99"},
                            "features": [{"type": "door", "centroid": [0, 0, 0]}]},
    "nested 100000 deep": "[" * 100_000 + "]" * 100_000,
    "a 5000-digit number": '{"frame": "map", "features": [{"type": "door", "centroid": [' + "9" * 5000 + ',0,0]}]}',
    "corners at 1e308": {"frame": "map", "features": [{"type": "door", "corners": [[1e308, 0, 0], [1e308, 0, 2],
                                                                                   [-1e308, 0, 2], [0, 0, 0]]}]},
    "20000 features": {"frame": "map", "features": [{"type": "door", "centroid": [i, 0, 1]} for i in range(20_000)]},
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_observations_exit_2_with_one_line(case: str, tmp_path: Path, capsys, office_path: Path) -> None:
    path = tmp_path / "OBS.json"
    content = BAD_INPUTS[case]
    if content is not None:
        path.write_text(content if isinstance(content, str) else json.dumps(content))
    rc, out, err = run(["localize", str(office_path), "--observations", str(path), "--json"], capsys)
    assert rc == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and err.startswith("macroloc: error:")


@pytest.mark.parametrize("args", [["localize", "nope.ifc", "--observations", "x.json"],
                                  ["features", "README.md"], ["features"], ["localize", "--method"],
                                  ["eval", "data/buildings/duplex.ifc", "--variant", "upside-down"]])
def test_bad_arguments_exit_2_with_one_line(args: list[str], capsys) -> None:
    rc, _, err = run(args, capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1


def test_unknown_method_is_a_user_error(tmp_path: Path, capsys, office_path: Path, office_model) -> None:
    obs = tmp_path / "OBS.json"
    obs.write_text(json.dumps(obs_doc(office_model, np.eye(4), "Level 1", 4)))
    rc, _, err = run(["localize", str(office_path), "--observations", str(obs), "--method", "magic"], capsys)
    assert rc == 2 and "unknown method" in err


def test_eval_compares_both_methods(capsys, fzk_path: Path) -> None:
    rc, out, _ = run(["eval", str(fzk_path), "--n", "4", "--variant", "gravity", "--json"], capsys)
    doc = json.loads(out)["variants"]["gravity"]
    assert rc == 0 and set(doc) >= {"paper", "robust", "table1_paper"}
    assert doc["robust"]["n"] == 4 and len(doc["table1_paper"]) == 4


def test_the_installed_command_runs_as_a_process(tmp_path: Path) -> None:
    p = subprocess.run([sys.executable, "-m", "macroloc.cli.main", "localize", "--help"], capture_output=True,
                       text=True)
    assert p.returncode == 0 and "ambiguous" in p.stdout


def _damaged_copies(fzk_path: Path, tmp_path: Path) -> dict[str, Path]:
    """FZK-Haus cut in half, and with one coordinate of a door's geometry replaced by the text NaN."""
    text = fzk_path.read_bytes()
    half = tmp_path / "half.ifc"
    half.write_bytes(text[: len(text) // 2])
    nan = tmp_path / "nan.ifc"
    nan.write_bytes(text.replace(b"#17343= IFCCARTESIANPOINT((0.835,", b"#17343= IFCCARTESIANPOINT((NaN,", 1))
    assert nan.read_bytes() != text
    return {"truncated": half, "NaN vertex": nan}


@pytest.mark.parametrize("case", ["truncated", "NaN vertex"])
def test_a_damaged_ifc_is_refused_with_one_line(case: str, fzk_path: Path, tmp_path: Path, capsys) -> None:
    rc, out, err = run(["features", str(_damaged_copies(fzk_path, tmp_path)[case]), "--json"], capsys)
    assert rc == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and ("truncated" in err or "damaged" in err), err


def test_a_door_with_an_absurd_vertex_is_dropped_and_counted(fzk_path: Path, tmp_path: Path) -> None:
    """A coordinate of 1e200 parses; the kernel would drop the faces it spans and shrink the door silently."""
    from macroloc.graph.bim_ifc import read_ifc_features

    huge = tmp_path / "huge.ifc"
    huge.write_bytes(fzk_path.read_bytes().replace(b"#17343= IFCCARTESIANPOINT((0.835,",
                                                   b"#17343= IFCCARTESIANPOINT((1.E200,", 1))
    features, report = read_ifc_features(huge)
    assert report["non_finite"] == ["1Oms875aH3Wg$9l65H2ZGw"]
    assert report["elements"] == len(features) + 1
    intact, _ = read_ifc_features(fzk_path)
    assert {f.id for f in intact} - {f.id for f in features} == {"1Oms875aH3Wg$9l65H2ZGw"}
