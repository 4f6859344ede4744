"""The service's Zenoh sessions: `open_session(cfg)` builds a session config from an optional JSON5 file plus the
typed overrides (peer mode on loopback, multicast and gossip scouting off by default), and checks what it exposes.
The key expressions and the publishers' encoding are the wire's (macroloc.proto.keys).
"""

from __future__ import annotations

import ipaddress
import json
import logging

import zenoh

from macroloc.graph.errors import UserInputError
from macroloc.service.config import ZenohConfig

log = logging.getLogger(__name__)
SECURE_PROTOCOLS = ("tls", "quic")  # encrypted and authenticated by the TLS configuration
LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe", "vsock")  # never leave the machine

def session_config(cfg: ZenohConfig) -> zenoh.Config:
    """A zenoh.Config: the JSON5 file (if any), then mode, endpoints and scouting from the typed config."""
    conf = zenoh.Config.from_file(str(cfg.config_file)) if cfg.config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    if cfg.connect:
        conf.insert_json5("connect/endpoints", json.dumps(cfg.connect))
    if cfg.listen:
        conf.insert_json5("listen/endpoints", json.dumps(cfg.listen))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    conf.insert_json5("scouting/gossip/enabled", json.dumps(cfg.gossip_scouting))
    check_no_tls_bypass(conf)
    return conf


def _endpoints(conf: zenoh.Config, path: str) -> list[str]:
    """The endpoints under connect/ or listen/: a list, or a list per mode."""
    value = json.loads(conf.get_json(path) or "null")
    if isinstance(value, dict):
        return [e for per_mode in value.values() for e in (per_mode or [])]
    return list(value or [])


def is_loopback_endpoint(endpoint: str) -> bool:
    """True for an endpoint that cannot be reached from another machine (loopback address or a local socket)."""
    protocol, _, address = endpoint.partition("/")
    if protocol in LOCAL_PROTOCOLS:
        return True
    host = address.split("#")[0].rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_no_tls_bypass(conf: zenoh.Config) -> None:
    """Refuse a configuration that sets up TLS but also connects or listens in the clear beyond this machine.

    With a TLS certificate configured, every endpoint that another machine can reach must be `tls/` or `quic/`;
    plain endpoints on loopback stay allowed (onboard processes reach the service there). Raises UserInputError.
    """
    if conf.get_json("transport/link/tls/root_ca_certificate") in (None, "null"):
        return
    for path in ("connect/endpoints", "listen/endpoints"):
        for endpoint in _endpoints(conf, path):
            if not endpoint.startswith(tuple(p + "/" for p in SECURE_PROTOCOLS)) and not is_loopback_endpoint(endpoint):
                raise UserInputError(f"zenoh: {path.split('/')[0]} endpoint {endpoint} would bypass the TLS "
                                     f"configuration: use tls/ or quic/ (plain endpoints only on loopback)")


def describe_exposure(conf: zenoh.Config) -> str:
    """One sentence for the log: who can reach this session's keys (and so put goals), from its endpoints."""
    listen = _endpoints(conf, "listen/endpoints")
    connect = _endpoints(conf, "connect/endpoints")
    if all(is_loopback_endpoint(e) for e in [*listen, *connect]):
        return f"goals and inputs are accepted from this machine only (listening on {', '.join(listen) or 'nothing'})"
    return (f"goals and inputs are accepted from whoever reaches {', '.join([*listen, *connect])}: "
            f"restrict them with the router's access control (deploy/zenoh/router.json5)")


def open_session(cfg: ZenohConfig) -> zenoh.Session:
    return zenoh.open(session_config(cfg))
