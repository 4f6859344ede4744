"""deploy/: the systemd unit passes `systemd-analyze verify`; Zenoh configs parse; the example config loads."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from macroloc.service.config import load_config
from tests.service.helpers import free_port

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def test_systemd_unit_verifies(tmp_path: Path) -> None:
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed on this machine")
    unit = (DEPLOY / "macroloc.service").read_text()
    for key in ("Restart=on-failure", "User=macroloc", "NoNewPrivileges=yes", "ProtectSystem=strict",
                "StateDirectory=macroloc", "ConfigurationDirectory=macroloc", "KillSignal=SIGTERM",
                "Type=notify", "WatchdogSec=", "MemoryMax=", "TasksMax="):
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
    conf.insert_json5("transport/auth/usrpwd/dictionary_file",
                      json.dumps(str(DEPLOY / "zenoh" / "credentials.example.txt")))
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


def test_tls_peer_config_refuses_a_plain_endpoint_beyond_loopback() -> None:
    from macroloc.graph.errors import UserInputError
    from macroloc.service.config import ZenohConfig
    from macroloc.service.zenoh_io import session_config

    tls_file = DEPLOY / "zenoh" / "peer-tls.json5"
    session_config(ZenohConfig(config_file=tls_file, listen=["tcp/127.0.0.1:7447"]))  # loopback stays allowed
    session_config(ZenohConfig(config_file=tls_file, connect=["tls/192.0.2.10:7447"], listen=[]))
    with pytest.raises(UserInputError, match="tcp/192.0.2.10:7447 would bypass the TLS"):
        session_config(ZenohConfig(config_file=tls_file, connect=["tcp/192.0.2.10:7447"], listen=[]))
    with pytest.raises(UserInputError, match="listen endpoint tcp/0.0.0.0:7447"):
        session_config(ZenohConfig(config_file=tls_file, listen=["tcp/0.0.0.0:7447"]))
    # without TLS nothing is refused: the plain peer file with the example config's (empty) overrides
    session_config(ZenohConfig(config_file=DEPLOY / "zenoh" / "peer.json5", listen=[]))


def test_serve_with_a_tls_bypass_exits_2_with_one_line(tmp_path: Path) -> None:
    config = tmp_path / "config.toml"
    config.write_text(f'[service]\nbuilding = "{DEPLOY.parent / "data" / "buildings" / "duplex.ifc"}"\n'
                      f'state_dir = "{tmp_path}"\n[zenoh]\nconnect = ["tcp/192.0.2.10:7447"]\nlisten = []\n'
                      f'config_file = "{DEPLOY / "zenoh" / "peer-tls.json5"}"\n')
    done = subprocess.run([str(Path(sys.executable).parent / "macroloc"), "serve", "--config", str(config)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "would bypass the TLS" in lines[0], done.stderr


def test_exposure_is_said_for_loopback_and_beyond() -> None:
    from macroloc.service.config import ZenohConfig
    from macroloc.service.zenoh_io import describe_exposure, session_config

    assert "this machine only" in describe_exposure(session_config(ZenohConfig()))
    assert "access control" in describe_exposure(session_config(ZenohConfig(listen=["tcp/0.0.0.0:7447"])))
