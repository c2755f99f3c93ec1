"""A running target's control socket, both ends: the server the target runs (:class:`ControlServer`,
one JSON object per line, answered with one JSON line; the commands are in sim_target/server.py's
docstring) and the client (:func:`send_control`, for ``hil target inject``, tests and the launcher).
Light: no pybullet here.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Protocol

from drivers.json_socket import JsonLineServer, SocketPathError, request_json_line
from sim_target.config import Fault, RunStart, TargetConfigError, parse_fault, parse_run_start

log = logging.getLogger(__name__)


class ControlTarget(Protocol):
    """What the control socket asks of the target (sim_target.server.TargetServer)."""

    def status(self) -> dict[str, Any]: ...

    def start_run(self, start: RunStart) -> None: ...

    def inject(self, fault: Fault) -> None: ...


def send_control(path: Path | str, command: dict[str, Any], timeout_s: float = 2.0) -> dict[str, Any]:
    """Send one command to a running target's control socket and return its reply (OSError when
    the socket cannot be reached or closes without answering)."""
    reply: dict[str, Any] = request_json_line(path, command, timeout_s)
    return reply


class ControlServer:
    """Serves the target's commands (:func:`_control_reply`) on ``path``. The socket handling is
    drivers.json_socket's, shared with the runtime's control socket: it removes only what it
    owns (a leftover socket nobody answers on; on close the socket it bound itself), never a
    regular file, a directory or a socket another target is serving on: the target refuses to
    start instead."""

    def __init__(self, path: Path, target: ControlTarget) -> None:
        self.path = Path(path)
        try:
            self._server = JsonLineServer(
                self.path,
                lambda line: _control_reply(target, line),
                in_use_by="another running target",
                thread_name="target-control",
                create_parent=True,  # /run/hil when no service made it
            )
        except SocketPathError as exc:
            raise TargetConfigError(f"control_socket {self.path}: {exc}") from None

    @property
    def native_thread_id(self) -> int | None:
        return self._server.native_thread_id

    def close(self) -> None:
        self._server.close()


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
