"""Line-oriented JSON over a Unix stream socket, both ends: the runtime's control socket
(hil_runtime/control.py) and the simulated target's (sim_target/control.py) are this, with their
own commands. Local only: no network address is involved. It lives in ``drivers`` because that is
the one package both ends of the rig import (docs/architecture.md); it knows nothing of CAN.

One JSON object per line in, one JSON line back. The server claims its path carefully: a leftover
*socket* nobody answers on (a killed process) is removed before binding; a regular file, a
directory, or a socket another process serves on is never touched (:class:`SocketPathError` says
which, and the caller refuses to start). The socket file is mode 0660 (owner and group: whoever may
write to it may command the process, nobody else). On close the server removes only the socket it
bound itself (same inode), not one another process has bound at the same path since.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import socketserver
import threading
from collections.abc import Callable
from pathlib import Path
from stat import S_ISSOCK
from typing import Any

_PROBE_TIMEOUT_S = 0.5  # how long "does anyone answer on this socket?" may take
_MAX_CHUNK = 65536


class SocketPathError(ValueError):
    """The socket path cannot be used; the message says why (the caller names the path and option)."""


def claim_socket_path(path: Path, in_use_by: str, create_parent: bool = False) -> None:
    """Make ``path`` free for bind, or raise :class:`SocketPathError` without deleting anything not
    ours. ``in_use_by`` names who would be serving on it ("another runtime (hil run)")."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        if create_parent:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise SocketPathError(f"cannot create {path.parent} ({exc.strerror or exc})") from None
        elif not path.parent.is_dir():
            raise SocketPathError(f"directory {path.parent} does not exist") from None
        return
    if not S_ISSOCK(mode):
        raise SocketPathError("exists and is not a socket; not removed (choose another path)")
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(_PROBE_TIMEOUT_S)
        try:
            probe.connect(str(path))
        except (ConnectionRefusedError, FileNotFoundError):
            path.unlink(missing_ok=True)  # a socket nobody serves: left by a killed process
            return
        except OSError as exc:
            raise SocketPathError(f"cannot check it ({exc.strerror or exc})") from None
    raise SocketPathError(f"in use by {in_use_by}")


class JsonLineServer:
    """Answers each request line with ``reply(line)`` (a JSON object), from daemon threads (one per
    connection); construction binds and starts serving, :meth:`close` stops and removes the socket."""

    def __init__(
        self,
        path: Path,
        reply: Callable[[str], dict[str, Any]],
        *,
        in_use_by: str,
        thread_name: str,
        create_parent: bool = False,
    ) -> None:
        self.path = Path(path)
        claim_socket_path(self.path, in_use_by, create_parent)

        class Handler(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                for raw in self.rfile:
                    line = raw.decode("utf-8", "replace").strip()
                    if line:
                        self.wfile.write((json.dumps(reply(line)) + "\n").encode())

        class Server(socketserver.ThreadingUnixStreamServer):
            daemon_threads = True

        old_umask = os.umask(0o117)  # the socket file: rw for owner and group only
        try:
            self._server = Server(str(self.path), Handler)
        except OSError as exc:
            raise SocketPathError(f"cannot bind ({exc.strerror or exc})") from None
        finally:
            os.umask(old_umask)
        stat = os.stat(self.path)
        self._identity = (stat.st_dev, stat.st_ino)
        self._thread = threading.Thread(
            target=self._server.serve_forever, kwargs={"poll_interval": 0.02}, name=thread_name, daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=2.0)
        try:
            stat = os.lstat(self.path)
        except OSError:
            return
        if (stat.st_dev, stat.st_ino) == self._identity:  # still ours: not replaced by another process
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()


def request_json_line(path: Path | str, request: dict[str, Any], timeout_s: float) -> Any:
    """Send ``request`` as one line and return the decoded reply line. OSError when the socket cannot
    be reached (FileNotFoundError: nobody made it) or closes without answering (ConnectionResetError);
    ValueError (json.JSONDecodeError) on a reply that is not JSON."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        sock.connect(str(path))
        sock.sendall((json.dumps(request) + "\n").encode())
        data = b""
        while not data.endswith(b"\n"):
            chunk = sock.recv(_MAX_CHUNK)
            if not chunk:
                break
            data += chunk
    if not data:
        raise ConnectionResetError(0, "the server closed the connection without answering")
    return json.loads(data)


__all__ = ["JsonLineServer", "SocketPathError", "claim_socket_path", "request_json_line"]
