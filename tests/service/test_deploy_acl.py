"""deploy/zenoh's routers, run as Python router-mode sessions on loopback: who may steer, who may speak for the service.

Each identity of the shipped ACL connects as a client with its user name (router.json5) or its certificate's common
name (router-tls.json5); every allowed put, subscription, query and liveliness token must work and every forbidden
one must be refused. A refusal is checked after an allowed message on the same key has arrived, plus a grace period,
so a slow machine cannot turn a delivery that merely came late into a pass.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest
import zenoh

from tests.service.helpers import free_port

DEPLOY = Path(__file__).resolve().parents[2] / "deploy" / "zenoh"
GRACE_S = 0.5
USERS = ("ground1", "macroloc-drone1", "drone1")


class Inbox:
    """Payloads received on one subscription, with a wait on a condition."""

    def __init__(self) -> None:
        self.payloads: list[bytes] = []
        self._cv = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cv:
            self.payloads.append(bytes(sample.payload.to_bytes()))
            self._cv.notify_all()

    def wait_for(self, payload: bytes, timeout_s: float = 10.0) -> bool:
        with self._cv:
            return self._cv.wait_for(lambda: payload in self.payloads, timeout=timeout_s)


def _client(endpoint: str, extra: dict) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    for path, value in extra.items():
        conf.insert_json5(path, json.dumps(value))
    return conf


@pytest.fixture(scope="module")
def usrpwd_router(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, dict[str, zenoh.Session]]]:
    """The shipped router.json5 on a loopback port, its credentials in a temporary dictionary; one client per user."""
    tmp = tmp_path_factory.mktemp("acl")
    (tmp / "credentials.txt").write_text("".join(f"{u}:pw-{u}\n" for u in USERS))
    router = zenoh.Config.from_file(str(DEPLOY / "router.json5"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router.insert_json5("listen/endpoints", json.dumps([endpoint]))
    router.insert_json5("scouting/gossip/enabled", "false")
    router.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(tmp / "credentials.txt")))
    with ExitStack() as stack:
        stack.enter_context(zenoh.open(router))
        yield endpoint, {u: stack.enter_context(zenoh.open(_client(endpoint, {
            "transport/auth/usrpwd/user": u, "transport/auth/usrpwd/password": f"pw-{u}"}))) for u in USERS}


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def _certificates(folder: Path, names: tuple[str, ...]) -> None:
    """A CA and one certificate per name (CN = name, SAN = localhost) signed by it."""
    _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca-key.pem", "-out", "ca.pem",
             "-days", "2", "-subj", "/CN=macroloc-test-ca", cwd=folder)
    (folder / "san.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    for name in names:
        _openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}-key.pem", "-out", f"{name}.csr",
                 "-subj", f"/CN={name}", cwd=folder)
        _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca-key.pem", "-CAcreateserial",
                 "-out", f"{name}-cert.pem", "-days", "2", "-extfile", "san.cnf", cwd=folder)


@pytest.fixture(scope="module")
def tls_sessions(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, zenoh.Session]]:
    """The shipped router-tls.json5 with a throw-away CA; one client per certificate common name."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: no certificates for the TLS router")
    tmp = tmp_path_factory.mktemp("acl-tls")
    _certificates(tmp, ("localhost", *USERS))
    router = zenoh.Config.from_file(str(DEPLOY / "router-tls.json5"))
    endpoint = f"tls/localhost:{free_port()}"
    router.insert_json5("listen/endpoints", json.dumps([endpoint.replace("localhost", "127.0.0.1")]))
    router.insert_json5("scouting/gossip/enabled", "false")
    for key, value in {"root_ca_certificate": "ca.pem", "listen_private_key": "localhost-key.pem",
                       "listen_certificate": "localhost-cert.pem"}.items():
        router.insert_json5(f"transport/link/tls/{key}", json.dumps(str(tmp / value)))
    with ExitStack() as stack:
        stack.enter_context(zenoh.open(router))
        yield {u: stack.enter_context(zenoh.open(_client(endpoint, {
            "transport/link/tls/root_ca_certificate": str(tmp / "ca.pem"),
            "transport/link/tls/connect_private_key": str(tmp / f"{u}-key.pem"),
            "transport/link/tls/connect_certificate": str(tmp / f"{u}-cert.pem"),
            "transport/link/tls/enable_mtls": True}))) for u in USERS}


def _subscribe(session: zenoh.Session, key: str, inbox: Inbox) -> zenoh.Subscriber:
    sub = session.declare_subscriber(key, inbox)
    time.sleep(0.3)  # the declaration reaches the router before the first put
    return sub


def _only_allowed_arrives(receiver: zenoh.Session, key: str, allowed: zenoh.Session,
                          forbidden: list[zenoh.Session]) -> None:
    inbox = Inbox()
    sub = _subscribe(receiver, key, inbox)
    try:
        for i, session in enumerate(forbidden):
            session.put(key, f"forbidden-{i}".encode())
        allowed.put(key, b"allowed")
        assert inbox.wait_for(b"allowed"), f"{key}: the allowed put never arrived"
        time.sleep(GRACE_S)
        assert inbox.payloads == [b"allowed"], f"{key}: forbidden puts arrived: {inbox.payloads}"
    finally:
        sub.undeclare()


def _check_policy(s: dict[str, zenoh.Session]) -> None:
    ground, service, drone = s["ground1"], s["macroloc-drone1"], s["drone1"]
    # only the ground station steers
    _only_allowed_arrives(service, "macroloc/drone1/goal", ground, [drone])
    # only the vehicle feeds its sensors (the ground station cannot inject frames)
    _only_allowed_arrives(service, "macroloc/drone1/imu", drone, [ground])
    # only the service speaks for the service: the vehicle and the ground station cannot spoof a pose or waypoints
    _only_allowed_arrives(ground, "macroloc/drone1/pose", service, [drone])
    _only_allowed_arrives(drone, "macroloc/drone1/waypoints", service, [ground])
    _only_allowed_arrives(ground, "macroloc/drone1/waypoints", service, [drone])

    # a vehicle sees only its own keys: drone1 subscribed to another vehicle's outputs receives nothing
    other = Inbox()
    sub = _subscribe(drone, "macroloc/drone2/**", other)
    watch = Inbox()
    watch_sub = _subscribe(ground, "macroloc/drone2/goal", watch)
    ground.put("macroloc/drone2/goal", b"for-drone2")
    time.sleep(GRACE_S * 2)
    assert other.payloads == [], "drone1 received drone2's traffic"
    sub.undeclare()
    watch_sub.undeclare()

    # only the service answers map and plan: a queryable declared by the vehicle is never asked
    fake = drone.declare_queryable("macroloc/drone1/map", lambda q: q.reply(q.key_expr, b"spoofed-map"))
    time.sleep(0.3)
    assert [r.ok for r in ground.get("macroloc/drone1/map", timeout=1.0) if r.ok is not None] == []
    fake.undeclare()
    real = service.declare_queryable("macroloc/drone1/map", lambda q: q.reply(q.key_expr, b"the-map"))
    time.sleep(0.3)
    answers = [bytes(r.ok.payload.to_bytes()) for r in ground.get("macroloc/drone1/map", timeout=5.0)
               if r.ok is not None]
    assert answers == [b"the-map"]
    real.undeclare()

    # the liveliness token: only the service's is seen
    spoof = drone.liveliness().declare_token("macroloc/drone1/alive")
    time.sleep(0.3)
    assert [r for r in ground.liveliness().get("macroloc/drone1/alive", timeout=1.0) if r.ok is not None] == []
    spoof.undeclare()
    token = service.liveliness().declare_token("macroloc/drone1/alive")
    time.sleep(0.3)
    alive = [str(r.ok.key_expr) for r in ground.liveliness().get("macroloc/drone1/alive", timeout=5.0)
             if r.ok is not None]
    assert alive == ["macroloc/drone1/alive"]
    token.undeclare()


def test_router_acl_by_user_name(usrpwd_router: tuple[str, dict[str, zenoh.Session]]) -> None:
    _check_policy(usrpwd_router[1])


def test_router_refuses_a_wrong_password(usrpwd_router: tuple[str, dict[str, zenoh.Session]]) -> None:
    with pytest.raises(zenoh.ZError):
        zenoh.open(_client(usrpwd_router[0], {"transport/auth/usrpwd/user": "ground1",
                                              "transport/auth/usrpwd/password": "wrong"}))


def test_tls_router_acl_by_certificate_name(tls_sessions: dict[str, zenoh.Session]) -> None:
    _check_policy(tls_sessions)
