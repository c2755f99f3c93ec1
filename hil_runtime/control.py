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

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Protocol

from drivers.json_socket import JsonLineServer, SocketPathError, request_json_line

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
    """Serves :func:`handle_command` on ``path`` from daemon threads (start before the loop's); the
    socket handling (claiming the path, mode 0660, removing only its own socket) is
    drivers.json_socket's, shared with the simulated target."""

    def __init__(self, path: Path, target: ControlTarget, avoid_cpus: Iterable[int] = ()) -> None:
        """``avoid_cpus``: the loop thread's CPUs (``loop.cpu_affinity``), never used for clients."""
        self.path = Path(path)
        try:
            self._server = JsonLineServer(
                self.path,
                lambda line: handle_command(target, line),
                in_use_by="another runtime (hil run)",
                thread_name="hil-control",
                create_parent=True,
                avoid_cpus=avoid_cpus,
            )
        except SocketPathError as exc:
            raise ControlError(f"control socket {self.path}: {exc}") from None

    def close(self) -> None:
        self._server.close()


def send_command(path: Path | str, command: str, timeout_s: float = 2.0) -> dict[str, Any]:
    """One request to a running daemon; :class:`ControlError` when nobody answers, the socket is
    another user's, or the daemon refuses (``{"ok": false, "error": ...}``)."""
    path = Path(path)
    try:
        reply = request_json_line(path, {"command": command}, timeout_s)
    except FileNotFoundError:
        raise ControlError(f"control socket {path}: no such file (is hil run running?)") from None
    except OSError as exc:
        raise ControlError(f"control socket {path}: {exc.strerror or exc}") from None
    except ValueError:
        raise ControlError(f"control socket {path}: unreadable reply") from None
    if not isinstance(reply, dict):
        raise ControlError(f"control socket {path}: unreadable reply (not a JSON object)")
    if reply.get("ok") is not True:
        raise ControlError(f"control socket {path}: {command} refused: {reply.get('error', 'no reason given')}")
    return reply
