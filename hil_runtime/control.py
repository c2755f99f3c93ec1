"""The daemon's local control socket: ``hil status``, ``hil reset``, ``hil stop`` talk to it.

A Unix stream socket (``control_socket`` in the config; under systemd ``/run/hil/...`` from
``RuntimeDirectory=``), mode 0660: whoever may write to it may stop and reset the arm, nobody
else, and nothing listens on the network. One JSON object per line in, one JSON line back::

    {"command": "status"}    -> {"ok": true, "state": "ACTIVE", "fault": null, "rate_hz": 999.8, ...}
    {"command": "reset"}     -> {"ok": true, "state": "FAULT"}   (the loop acts at its next look)
    {"command": "activate"}  -> {"ok": true, ...}
    {"command": "stop"}      -> {"ok": true, ...}

Requests only set flags on the runtime (:meth:`Runtime.request_reset` ...); the loop's thread
does the work, so nothing here touches the bus.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import socketserver
import threading
from pathlib import Path
from typing import Any, Protocol

COMMANDS = ("status", "reset", "activate", "stop")


class ControlTarget(Protocol):
    def status(self) -> dict[str, Any]: ...

    def request_stop(self) -> None: ...

    def request_reset(self) -> None: ...

    def request_activate(self) -> None: ...


class ControlError(RuntimeError):
    """The daemon's control socket could not be reached or answered badly: one line, exit 2."""

    exit_code = 2


def handle_command(target: ControlTarget, line: str) -> dict[str, Any]:
    try:
        request = json.loads(line)
    except json.JSONDecodeError as exc:
        return {"ok": False, "error": f"not JSON: {exc.msg}"}
    command = request.get("command") if isinstance(request, dict) else None
    if command not in COMMANDS:
        return {"ok": False, "error": f"unknown command {command!r} (known: {', '.join(COMMANDS)})"}
    if command == "reset":
        target.request_reset()
    elif command == "activate":
        target.request_activate()
    elif command == "stop":
        target.request_stop()
    return {"ok": True, **target.status()}


class ControlServer:
    """Serves :func:`handle_command` on ``path`` from one daemon thread (start before the loop's)."""

    def __init__(self, path: Path, target: ControlTarget) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists() or self.path.is_symlink():
            if _answers(self.path):
                raise ControlError(f"control socket {self.path}: another runtime is listening on it")
            self.path.unlink()  # stale, from a process that died

        class Handler(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                for raw in self.rfile:
                    line = raw.decode("utf-8", "replace").strip()
                    if not line:
                        continue
                    reply = handle_command(target, line)
                    self.wfile.write((json.dumps(reply) + "\n").encode())

        class Server(socketserver.ThreadingUnixStreamServer):
            daemon_threads = True

        old_umask = os.umask(0o117)  # the socket file: rw for owner and group only
        try:
            self._server = Server(str(self.path), Handler)
        except OSError as exc:
            raise ControlError(f"control socket {self.path}: {exc.strerror or exc}") from None
        finally:
            os.umask(old_umask)
        self._thread = threading.Thread(
            target=self._server.serve_forever, kwargs={"poll_interval": 0.02}, name="hil-control", daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=2.0)
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()


def _answers(path: Path) -> bool:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(0.5)
        try:
            sock.connect(str(path))
        except OSError:
            return False
    return True


def send_command(path: Path | str, command: str, timeout_s: float = 2.0) -> dict[str, Any]:
    """One request to a running daemon; :class:`ControlError` when nobody answers."""
    path = Path(path)
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(timeout_s)
            sock.connect(str(path))
            sock.sendall((json.dumps({"command": command}) + "\n").encode())
            data = b""
            while not data.endswith(b"\n"):
                chunk = sock.recv(65536)
                if not chunk:
                    break
                data += chunk
    except FileNotFoundError:
        raise ControlError(f"control socket {path}: no such file (is hil run running?)") from None
    except OSError as exc:
        raise ControlError(f"control socket {path}: {exc.strerror or exc}") from None
    try:
        reply = json.loads(data)
    except json.JSONDecodeError:
        raise ControlError(f"control socket {path}: unreadable reply") from None
    if not isinstance(reply, dict):
        raise ControlError(f"control socket {path}: unreadable reply (not a JSON object)")
    return reply
