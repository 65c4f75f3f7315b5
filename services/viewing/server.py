"""The Rerun web viewer served on 127.0.0.1 only (`fp view --serve`) (docs/design.md §7 stack notes).

rerun-sdk's Python helpers cannot do that: ``rr.serve_web_viewer`` and ``rr.serve_grpc`` take no bind
address and listen on 0.0.0.0 (checked in 0.41; no environment variable changes it), so anyone on the
network could read the recording. The ``rerun`` executable shipped in the same wheel (``rerun_cli``)
can: ``rerun --serve-web --bind 127.0.0.1`` binds both its HTTP server (the web viewer's page and
Wasm, ``--port``) and its gRPC proxy (the data, ``--grpc-port``) to loopback. :func:`serve_loopback`
runs it as a child process, checks the child's listening sockets (``/proc/net/tcp*``,
:func:`listening_addresses`) and refuses to go on if one is not loopback. The bind address is not an
option on purpose: to look from another machine, forward the two ports over SSH
(``ssh -L 9090:127.0.0.1:9090 -L 9876:127.0.0.1:9876 HOST``).
"""

from __future__ import annotations

import ctypes
import importlib.util
import ipaddress
import logging
import math
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any
from urllib.parse import quote

__all__ = [
    "DEFAULT_GRPC_PORT",
    "DEFAULT_WEB_PORT",
    "LOOPBACK",
    "LoopbackViewer",
    "check_ports",
    "listening_addresses",
    "rerun_executable",
    "serve_loopback",
    "serve_until_stopped",
]

log = logging.getLogger("fp.viewer")

LOOPBACK = "127.0.0.1"
DEFAULT_WEB_PORT = 9090
DEFAULT_GRPC_PORT = 9876


def rerun_executable() -> Path:
    """The ``rerun`` executable of the installed rerun-sdk wheel (``RERUN_CLI_PATH`` overrides it, as for
    ``python -m rerun_cli``)."""
    override = os.environ.get("RERUN_CLI_PATH")
    if override:
        path = Path(override)
    else:
        spec = importlib.util.find_spec("rerun_cli")
        if spec is None or not spec.submodule_search_locations:
            raise FileNotFoundError("rerun_cli: not installed; reinstall rerun-sdk (it ships the rerun executable)")
        path = Path(next(iter(spec.submodule_search_locations))) / ("rerun.exe" if sys.platform == "win32" else "rerun")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no rerun executable; reinstall rerun-sdk or set RERUN_CLI_PATH")
    return path


def _proc_net_address(hex_addr: str) -> str:
    """``0100007F`` (IPv4) or 32 hex digits (IPv6) of /proc/net/tcp*, each 32-bit word in host order."""
    raw = bytes.fromhex(hex_addr)
    words = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4)) if sys.byteorder == "little" else raw
    return str(ipaddress.ip_address(words))


def listening_addresses(pid: int | None = None, port: int | None = None) -> list[tuple[str, int]] | None:
    """(IP, port) of the TCP sockets in LISTEN state, read from ``/proc/net/tcp`` and ``tcp6``: those of
    process ``pid`` (all the network namespace's when None), on ``port`` only if given. None where
    ``/proc`` does not exist (not Linux)."""
    if not Path("/proc/net/tcp").exists():
        return None
    inodes: set[str] | None = None
    if pid is not None:
        inodes = set()
        try:
            fds = list(Path(f"/proc/{pid}/fd").iterdir())
        except FileNotFoundError:  # the process is gone
            return []
        for fd in fds:
            try:
                target = os.readlink(fd)
            except OSError:  # closed meanwhile
                continue
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    out: list[tuple[str, int]] = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        if not Path(table).exists():
            continue
        for line in Path(table).read_text().splitlines()[1:]:
            cols = line.split()
            if len(cols) < 10 or cols[3] != "0A":  # 0A: TCP_LISTEN
                continue
            addr, port_hex = cols[1].rsplit(":", 1)
            p = int(port_hex, 16)
            if (port is None or p == port) and (inodes is None or cols[9] in inodes):
                out.append((_proc_net_address(addr), p))
    return out


def _check_port(option: str, port: int) -> None:
    if not 1 <= port <= 65535:
        raise ValueError(f"{option}: expected a TCP port 1…65535, got {port}")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((LOOPBACK, port))
        except OSError as exc:
            raise ValueError(f"{option}: {LOOPBACK}:{port} is not free ({exc.strerror}); give another port") from None


def check_ports(port: int, grpc_port: int) -> None:
    """ValueError naming the option unless both ports are valid, distinct and free on 127.0.0.1."""
    if port == grpc_port:
        raise ValueError(f"--port and --grpc-port: expected two different ports, got {port} twice")
    _check_port("--port", port)
    _check_port("--grpc-port", grpc_port)


def _accepts(port: int) -> bool:
    try:
        with socket.create_connection((LOOPBACK, port), timeout=0.5):
            return True
    except OSError:
        return False


def _listening(pid: int, ports: set[int]) -> bool:
    """Whether process ``pid`` listens on all ``ports`` (its own sockets, from /proc; elsewhere: whether
    the ports accept connections on 127.0.0.1)."""
    own = listening_addresses(pid)
    if own is None:
        return all(_accepts(p) for p in ports)
    return ports <= {p for _, p in own}


@dataclass
class LoopbackViewer:
    """A running ``rerun --serve-web --bind 127.0.0.1`` child: web viewer on ``web_port``, gRPC proxy
    (recording data) on ``grpc_port``. Stop it with `stop` (or use it as a context manager)."""

    proc: subprocess.Popen[bytes]
    web_port: int
    grpc_port: int
    log: IO[bytes]

    @property
    def grpc_url(self) -> str:
        """The proxy's URL, for ``rr.GrpcSink`` or ``rerun --connect``."""
        return f"rerun+http://{LOOPBACK}:{self.grpc_port}/proxy"

    @property
    def url(self) -> str:
        """The page to open in a browser: the web viewer, connected to the proxy."""
        return f"http://{LOOPBACK}:{self.web_port}/?url={quote(self.grpc_url, safe='')}"

    def log_tail(self, n: int = 1500) -> str:
        """The end of the child's output, without terminal colours."""
        self.log.flush()
        self.log.seek(0)
        text = self.log.read().decode(errors="replace")
        return re.sub(r"\x1b\[[0-9;]*m", "", text)[-n:].strip()

    def stop(self, timeout: float = 10.0) -> int:
        """Terminate the child (SIGTERM, then SIGKILL after ``timeout`` s); returns its exit code."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        self.log.close()
        return int(self.proc.returncode)

    def __enter__(self) -> LoopbackViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _die_with_parent() -> None:
    """In the rerun child (Linux): receive SIGTERM when the parent dies, even by SIGKILL, so a killed
    `fp view --serve` never leaves a server holding its ports (prctl PR_SET_PDEATHSIG)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass  # not Linux: the parent's own cleanup stops the child


def serve_loopback(
    rrd: str | Path | None = None,
    *,
    port: int = DEFAULT_WEB_PORT,
    grpc_port: int = DEFAULT_GRPC_PORT,
    server_memory_limit: str = "1GiB",
    timeout: float = 30.0,
) -> LoopbackViewer:
    """Start the Rerun web viewer and its gRPC proxy bound to 127.0.0.1 only, serving ``rrd`` (or, without
    one, whatever an SDK logs to `LoopbackViewer.grpc_url`). Returns once both ports accept connections
    and the child's listening sockets are checked to be loopback (Linux); raises ValueError for a bad or
    busy port, ChildProcessError when rerun exits or listens elsewhere, TimeoutError after ``timeout`` s.
    The child is stopped if the calling *thread* ends (PR_SET_PDEATHSIG): call it from a thread that
    lives as long as the viewer should."""
    check_ports(port, grpc_port)
    if rrd is not None and not Path(rrd).is_file():
        raise FileNotFoundError(f"{rrd}: no such .rrd file")
    cmd = [
        str(rerun_executable()),
        "--serve-web",
        "--bind",
        LOOPBACK,
        "--web-viewer-port",
        str(port),
        "--port",
        str(grpc_port),
        "--server-memory-limit",
        server_memory_limit,
    ]
    if rrd is not None:
        cmd.append(str(Path(rrd).resolve()))
    log_file = tempfile.TemporaryFile()
    proc = subprocess.Popen(
        cmd,
        stdin=subprocess.DEVNULL,
        stdout=log_file,
        stderr=subprocess.STDOUT,
        env={**os.environ, "NO_COLOR": "1"},
        preexec_fn=_die_with_parent,
    )
    viewer = LoopbackViewer(proc, port, grpc_port, log_file)
    deadline = time.monotonic() + timeout
    while not _listening(proc.pid, {port, grpc_port}):
        if proc.poll() is not None:
            tail = viewer.log_tail()
            viewer.stop()
            raise ChildProcessError(f"rerun --serve-web exited with code {proc.returncode}: {tail}")
        if time.monotonic() > deadline:
            viewer.stop()
            raise TimeoutError(
                f"rerun --serve-web: ports {port} (--port) and {grpc_port} (--grpc-port) not "
                f"open on {LOOPBACK} after {timeout:g} s"
            )
        time.sleep(0.05)
    listening = listening_addresses(proc.pid)
    exposed = [a for a in listening or [] if not ipaddress.ip_address(a[0]).is_loopback]
    if listening is None:
        log.warning("cannot list the sockets of rerun (pid %d) here: loopback binding not checked", proc.pid)
    if exposed:
        viewer.stop()
        raise ChildProcessError(f"rerun --serve-web listens on {exposed}, not only on {LOOPBACK}; stopped it")
    log.info("rerun web viewer on %s (pid %d), listening on %s", viewer.url, proc.pid, listening)
    return viewer


def serve_until_stopped(viewer: LoopbackViewer, stop: Any, duration: float | None) -> None:
    """Block until ``stop`` is set, ``duration`` s pass or the viewer's process ends (an error)."""
    deadline = time.monotonic() + duration if duration else math.inf
    while not stop.wait(0.2) and time.monotonic() < deadline:
        if viewer.proc.poll() is not None:
            if stop.wait(0.5):  # Ctrl-C in a terminal reaches the child too; not an error
                return
            raise ChildProcessError(f"rerun --serve-web exited with code {viewer.proc.returncode}: {viewer.log_tail()}")
