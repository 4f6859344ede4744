"""deploy/: the systemd unit passes `systemd-analyze verify`; Zenoh configs parse; the example config loads."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from service.config import load_config
from tests.service.helpers import free_port

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def test_systemd_unit_verifies(tmp_path: Path) -> None:
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed on this machine")
    unit = (DEPLOY / "macroloc.service").read_text()
    for key in ("Restart=on-failure", "User=macroloc", "NoNewPrivileges=yes", "ProtectSystem=strict",
                "StateDirectory=macroloc", "ConfigurationDirectory=macroloc", "KillSignal=SIGTERM"):
        assert key in unit, key
    # verify checks that ExecStart exists: point it at this checkout's entry point
    local = tmp_path / "macroloc.service"
    local.write_text(unit.replace("/opt/macroloc/.venv/bin/macroloc", str(Path(sys.executable).parent / "macroloc")))
    done = subprocess.run(["systemd-analyze", "verify", str(local)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize("name", ["peer.json5", "peer-tls.json5", "router.json5", "router-tls.json5"])
def test_zenoh_configs_parse(name: str) -> None:
    zenoh.Config.from_file(str(DEPLOY / "zenoh" / name))


def test_router_config_with_access_control_opens() -> None:
    conf = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "router.json5"))
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{free_port()}"]))
    with zenoh.open(conf) as session:
        assert str(session.zid())


def test_example_config_and_environment_file_load(monkeypatch: pytest.MonkeyPatch) -> None:
    for line in (DEPLOY / "macroloc.env").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            key, value = line.split("=", 1)
            monkeypatch.setenv(key, value)
    cfg = load_config(DEPLOY / "config.toml")
    assert cfg.service.vehicle == "drone1" and str(cfg.service.state_dir) == "/var/lib/macroloc"
    assert cfg.zenoh.config_file is not None and cfg.zenoh.mode == "peer"
