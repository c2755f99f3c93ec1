"""The client side of a running target's control socket: light (no pybullet), for ``hil target inject``."""

from __future__ import annotations

import json
import socket
from pathlib import Path
from typing import Any


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
