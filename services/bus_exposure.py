"""What a bus session exposes, and zenoh's errors in one line (docs/wire.md, "Securing the bus").

``services.bus`` refuses a listen endpoint that other hosts can reach unless ``allow_remote`` is set
(:func:`remote_endpoints` of :func:`listen_endpoints`, zenoh's per-mode defaults included) and then
prints :func:`bus_warnings`; :func:`config_file` reads a ``--zenoh-config`` file and :func:`zerror_line`
turns a zenoh error (a Rust message with its source location, a JSON5 parser report) into one line.
"""

from __future__ import annotations

import ipaddress
import json
import os
import re

import zenoh

__all__ = ["bus_warnings", "config_file", "is_loopback", "listen_endpoints", "remote_endpoints", "zerror_line"]

_LOOPBACK_NAMES = {"localhost", "ip6-localhost", "ip6-loopback"}
_LOCAL_PROTOCOLS = {"unixsock-stream", "unixpipe"}


def is_loopback(endpoint: str) -> bool:
    """True for an endpoint only this host can reach: a loopback address or name, or a Unix socket/pipe."""
    proto, _, rest = endpoint.partition("/")
    if proto in _LOCAL_PROTOCOLS:
        return True
    address = rest.split("?", 1)[0].split("#", 1)[0]
    host = address.rsplit(":", 1)[0] if ":" in address else address
    host = host.strip("[]").lower()
    if host in _LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name, or no address at all: it may be reachable from elsewhere


def listen_endpoints(cfg: zenoh.Config) -> list[str]:
    """The endpoints a session of ``cfg`` will listen on, zenoh's per-mode defaults included (a router
    with no ``listen/endpoints`` listens on ``tcp/[::]:7447``, every interface)."""
    mode = json.loads(cfg.get_json("mode") or "null") or "peer"
    eps = json.loads(cfg.get_json("listen/endpoints") or "null")
    if isinstance(eps, dict):
        eps = eps.get(mode, [])
    return [str(e) for e in eps or []]


def remote_endpoints(endpoints: list[str]) -> list[str]:
    """The endpoints of ``endpoints`` that other hosts may reach (not loopback, not a local socket)."""
    return [e for e in endpoints if not is_loopback(e)]


def bus_warnings(cfg: zenoh.Config) -> list[str]:
    """What a session of ``cfg`` exposes: remote listeners, and then whether they lack authentication or TLS."""
    remote = remote_endpoints(listen_endpoints(cfg))
    if not remote:
        return []
    notes = [f"listening on {', '.join(remote)}: other hosts can reach this node"]
    if json.loads(cfg.get_json("transport/auth/usrpwd/dictionary_file") or "null") is None:
        notes.append("no user/password authentication (transport/auth/usrpwd/dictionary_file)")
    plain = [e for e in remote if e.partition("/")[0] not in ("tls", "quic")]
    if plain:
        notes.append(f"not encrypted ({', '.join(plain)}; use tls/ endpoints)")
    if not json.loads(cfg.get_json("access_control/enabled") or "false"):
        notes.append("no access control rules")
    return notes


def config_file(path: str) -> zenoh.Config:
    if not os.path.isfile(path):
        raise ValueError(f"--zenoh-config: no such file {path!r}")
    try:
        return zenoh.Config.from_file(path)
    except zenoh.ZError as exc:
        raise ValueError(f"--zenoh-config {path}: not a valid zenoh configuration: {zerror_line(exc)}") from None


def zerror_line(exc: BaseException) -> str:
    """One line from a zenoh error: no Rust source location; a JSON5 syntax error as its position and message."""
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?", "", str(exc)).strip()
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    loc = next((ln[3:].strip() for ln in lines if ln.startswith("-->")), None)
    msg = next((ln[1:].strip() for ln in lines if ln.startswith("=")), None)
    if loc and msg:
        return f"at line:column {loc}: {msg}"
    return " ".join(lines) or type(exc).__name__
