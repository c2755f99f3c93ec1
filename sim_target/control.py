"""A running target's control socket, both ends: the server the target runs (:class:`ControlServer`,
one JSON object per line, answered with one JSON line; the commands are in sim_target/server.py's
docstring) and the client (:func:`send_control`, for ``hil target inject``, tests and the launcher).
Light: no pybullet here.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import socketserver
import threading
from pathlib import Path
from stat import S_ISSOCK
from typing import Any, Protocol

from sim_target.config import Fault, RunStart, TargetConfigError, parse_fault, parse_run_start

log = logging.getLogger(__name__)


class ControlTarget(Protocol):
    """What the control socket asks of the target (sim_target.server.TargetServer)."""

    def status(self) -> dict[str, Any]: ...

    def start_run(self, start: RunStart) -> None: ...

    def inject(self, fault: Fault) -> None: ...


def send_control(path: Path | str, command: dict[str, Any], timeout_s: float = 2.0) -> dict[str, Any]:
    """Send one command to a running target's control socket and return its reply."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        sock.connect(str(path))
        sock.sendall((json.dumps(command) + "\n").encode())
        reply = b""
        while not reply.endswith(b"\n"):
            chunk = sock.recv(65536)
            if not chunk:
                break
            reply += chunk
    if not reply:
        raise ConnectionResetError(0, "the target closed the connection without answering")
    return json.loads(reply)


class ControlServer:
    """Line-oriented JSON over a Unix socket: local only, no network address involved.

    It removes only what it owns: a leftover *socket* that nobody answers on (a killed run) before
    binding, and on close the socket it bound itself (same inode). A regular file, a directory or a
    socket another target is serving on is never touched: the target refuses to start instead."""

    def __init__(self, path: Path, target: ControlTarget) -> None:
        self.path = Path(path)
        _claim_socket_path(self.path)

        class Handler(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                for raw in self.rfile:
                    reply = _control_reply(target, raw.decode(errors="replace"))
                    self.wfile.write((json.dumps(reply) + "\n").encode())

        try:
            self._server = socketserver.ThreadingUnixStreamServer(str(self.path), Handler)
        except OSError as exc:
            raise TargetConfigError(f"control_socket {self.path}: cannot bind ({exc.strerror or exc})") from None
        stat = os.stat(self.path)
        self._identity = (stat.st_dev, stat.st_ino)
        self._server.daemon_threads = True
        self._thread = threading.Thread(target=self._server.serve_forever, name="target-control", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        try:
            stat = os.lstat(self.path)
        except OSError:
            return
        if (stat.st_dev, stat.st_ino) == self._identity:  # still ours: not replaced by another target
            self.path.unlink(missing_ok=True)


def _claim_socket_path(path: Path) -> None:
    """Make ``path`` free for bind, or refuse (TargetConfigError) without deleting anything not ours."""
    try:
        stat = os.lstat(path)
    except FileNotFoundError:
        if not path.parent.is_dir():
            raise TargetConfigError(f"control_socket {path}: directory {path.parent} does not exist") from None
        return
    if not S_ISSOCK(stat.st_mode):
        raise TargetConfigError(f"control_socket {path}: exists and is not a socket; not removed (choose another path)")
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(0.5)
        try:
            probe.connect(str(path))
        except (ConnectionRefusedError, FileNotFoundError):
            path.unlink(missing_ok=True)  # a socket nobody serves: left by a killed run
            return
        except OSError as exc:
            raise TargetConfigError(f"control_socket {path}: cannot check it ({exc.strerror or exc})") from None
    raise TargetConfigError(f"control_socket {path}: in use by another running target")


def _control_reply(target: ControlTarget, line: str) -> dict[str, Any]:
    try:
        data = json.loads(line)
        if isinstance(data, dict) and data.get("kind") == "status":
            return {"ok": True, **target.status()}
        if isinstance(data, dict) and data.get("kind") == "start":
            target.start_run(parse_run_start(data, "control"))
            return {"ok": True}
        target.inject(parse_fault(data, "control"))
        return {"ok": True}
    except json.JSONDecodeError as exc:
        return {"ok": False, "error": f"control: not JSON ({exc.msg})"}
    except TargetConfigError as exc:
        return {"ok": False, "error": str(exc)}
    except Exception as exc:
        log.exception("control command failed: %s", line.strip()[:200])
        return {"ok": False, "error": f"control: {type(exc).__name__}: {exc}"}
