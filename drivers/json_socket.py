"""Line-oriented JSON over a Unix stream socket, both ends: the runtime's control socket
(hil_runtime/control.py) and the simulated target's (sim_target/control.py) are this, with their
own commands. Local only: no network address is involved. It lives in ``drivers`` because that is
the one package both ends of the rig import (docs/architecture.md); it knows nothing of CAN.

One JSON object per line in, one JSON line back, from one server thread with bounded clients,
idle time-outs and refused over-long or over-nested lines (:class:`JsonLineServer`). The client
talks only to a socket its own user (or root, or a service's private runtime directory) owns
(drivers/ownership.py). The server claims its path carefully: a leftover
*socket* nobody answers on (a killed process) is removed before binding; a regular file, a
directory, or a socket another process serves on is never touched (:class:`SocketPathError` says
which, and the caller refuses to start). The socket file is mode 0660 (owner and group: whoever may
write to it may command the process, nobody else). On close the server removes only the socket it
bound itself (same inode), not one another process has bound at the same path since.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import selectors
import socket
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from stat import S_ISSOCK
from typing import Any, cast

from drivers.ownership import OwnershipError, check_server_peer, check_socket_owner

log = logging.getLogger(__name__)

_PROBE_TIMEOUT_S = 0.5  # how long "does anyone answer on this socket?" may take
_MAX_CHUNK = 65536
_POLL_S = 0.05  # the server thread looks at idle clients and close() this often
MAX_CLIENTS = 16  # connections served at once; more are refused (a line saying so)
IDLE_TIMEOUT_S = 10.0  # a connection without a request for this long is closed
MAX_LINE_BYTES = 65536  # a request line longer than this is refused unparsed
MAX_DEPTH = 32  # arrays/objects nested deeper are refused unparsed (the commands need 3)
MAX_REPLY_BYTES = 1 << 20  # a client stops reading a reply this long


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
                path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)  # private, as the bus's
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
    """Answers each request line with ``reply(line)`` (a JSON object) from one thread that serves
    every connection (a selector): at most ``max_clients`` at once (a newcomer closes the one idle
    longest, so idle connections never lock a command out),
    each closed after ``idle_timeout_s`` without a request, a line longer than ``max_line_bytes``
    or nested deeper than ``MAX_DEPTH`` answered with an error, never parsed. So no client, or
    3,000 of them, costs more than this one thread; ``avoid_cpus`` keeps it off the control loop's
    CPUs. Construction binds and starts serving, :meth:`close` stops and removes the socket."""

    def __init__(
        self,
        path: Path,
        reply: Callable[[str], dict[str, Any]],
        *,
        in_use_by: str,
        thread_name: str,
        create_parent: bool = False,
        max_clients: int = MAX_CLIENTS,
        idle_timeout_s: float = IDLE_TIMEOUT_S,
        max_line_bytes: int = MAX_LINE_BYTES,
        avoid_cpus: Iterable[int] = (),
    ) -> None:
        self.path = Path(path)
        self._reply = reply
        self._max_clients = max_clients
        self._idle_timeout_s = idle_timeout_s
        self._max_line_bytes = max_line_bytes
        self._avoid_cpus = frozenset(avoid_cpus)
        claim_socket_path(self.path, in_use_by, create_parent)
        listen = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old_umask = os.umask(0o117)  # the socket file: rw for owner and group only
        try:
            listen.bind(str(self.path))
            listen.listen(64)
        except OSError as exc:
            listen.close()
            raise SocketPathError(f"cannot bind ({exc.strerror or exc})") from None
        finally:
            os.umask(old_umask)
        listen.setblocking(False)
        self._listen = listen
        stat = os.stat(self.path)
        self._identity = (stat.st_dev, stat.st_ino)
        self._stop = threading.Event()
        self._clients: dict[socket.socket, _Client] = {}
        self._selector = selectors.DefaultSelector()
        self._selector.register(listen, selectors.EVENT_READ)
        self.evicted = 0  # connections closed to make room for a newer one (too many clients)
        self.timed_out = 0  # connections closed for idling
        self._thread = threading.Thread(target=self._serve, name=thread_name, daemon=True)
        self._thread.start()

    @property
    def client_count(self) -> int:
        return len(self._clients)

    @property
    def native_thread_id(self) -> int | None:
        """The serving thread's kernel id (for per-thread scheduling settings), None before it runs."""
        return self._thread.native_id

    def _serve(self) -> None:
        if self._avoid_cpus and hasattr(os, "sched_setaffinity"):
            allowed = os.sched_getaffinity(0) - self._avoid_cpus
            if allowed:
                os.sched_setaffinity(0, allowed)  # this thread only (Linux: pid 0 is the caller)
        while not self._stop.is_set():
            try:
                for key, _events in self._selector.select(_POLL_S):
                    if key.fileobj is self._listen:
                        self._accept()
                    else:
                        self._read(cast(socket.socket, key.fileobj))
            except Exception as exc:  # noqa: BLE001 - the server thread must outlive any one client
                log.warning("control socket %s: %s: %s", self.path, type(exc).__name__, exc)
            now = time.monotonic()
            for sock, client in list(self._clients.items()):
                if now - client.last_active_s > self._idle_timeout_s:
                    self.timed_out += 1
                    self._drop(sock)
        for sock in list(self._clients):
            self._drop(sock)

    def _accept(self) -> None:
        while True:
            try:
                sock, _ = self._listen.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # EMFILE: out of descriptors; the next round tries again
                log.warning("control socket %s: accept failed: %s", self.path, exc)
                return
            sock.setblocking(False)
            if len(self._clients) >= self._max_clients:
                # Full: the client idle the longest makes room. Refusing the newcomer instead would
                # let a few idle connections lock the operator's `hil stop` out.
                oldest = min(self._clients, key=lambda s: self._clients[s].last_active_s)
                self.evicted += 1
                self._send(oldest, {"ok": False, "error": f"closed: too many clients (at most {self._max_clients})"})
                self._drop(oldest)
            self._clients[sock] = _Client(time.monotonic())
            self._selector.register(sock, selectors.EVENT_READ)

    def _read(self, sock: socket.socket) -> None:
        client = self._clients.get(sock)
        if client is None:
            return
        try:
            chunk = sock.recv(_MAX_CHUNK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            chunk = b""
        if not chunk:
            self._drop(sock)
            return
        client.last_active_s = time.monotonic()
        client.buffer += chunk
        while b"\n" in client.buffer:
            raw, _, client.buffer = client.buffer.partition(b"\n")
            if not self._answer(sock, raw):
                return
        if len(client.buffer) > self._max_line_bytes:
            self._send(sock, {"ok": False, "error": f"request line over {self._max_line_bytes} bytes"})
            self._drop(sock)

    def _answer(self, sock: socket.socket, raw: bytes) -> bool:
        """Reply to one line; False when the client was dropped."""
        if len(raw) > self._max_line_bytes:
            answer: dict[str, Any] = {"ok": False, "error": f"request line over {self._max_line_bytes} bytes"}
        else:
            line = raw.decode("utf-8", "replace").strip()
            if not line:
                return True
            answer = self._safe_reply(line)
        if not self._send(sock, answer):
            self._drop(sock)
            return False
        return True

    def _safe_reply(self, line: str) -> dict[str, Any]:
        if json_depth(line) > MAX_DEPTH:
            return {"ok": False, "error": f"request nested deeper than {MAX_DEPTH} levels"}
        try:
            return self._reply(line)
        except RecursionError:
            return {"ok": False, "error": "request nested too deep"}
        except Exception as exc:  # noqa: BLE001 - a bad request never stops the server
            log.warning("control socket %s: request failed: %s: %s", self.path, type(exc).__name__, exc)
            return {"ok": False, "error": f"{type(exc).__name__}: {exc}"}

    def _send(self, sock: socket.socket, answer: dict[str, Any]) -> bool:
        try:
            data = (json.dumps(answer) + "\n").encode()
        except (TypeError, ValueError) as exc:
            data = (json.dumps({"ok": False, "error": f"unserialisable reply: {exc}"}) + "\n").encode()
        try:
            sent = sock.send(data, socket.MSG_NOSIGNAL)
        except OSError:  # BlockingIOError: a client that never reads its replies; EPIPE: gone
            return False
        return sent == len(data)

    def _drop(self, sock: socket.socket) -> None:
        self._clients.pop(sock, None)
        with contextlib.suppress(KeyError, ValueError):
            self._selector.unregister(sock)
        sock.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._selector.close()
        self._listen.close()
        try:
            stat = os.lstat(self.path)
        except OSError:
            return
        if (stat.st_dev, stat.st_ino) == self._identity:  # still ours: not replaced by another process
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()


@dataclass
class _Client:
    last_active_s: float
    buffer: bytes = b""


_STRING = re.compile(r'"(?:\\.|[^"\\])*"')


def json_depth(text: str) -> int:
    """The deepest nesting of arrays and objects in ``text`` (strings skipped), without parsing."""
    depth = deepest = 0
    for ch in _STRING.sub("", text):
        if ch in "[{":
            depth += 1
            if depth > deepest:
                deepest = depth
        elif ch in "]}":
            depth -= 1
    return deepest


def request_json_line(path: Path | str, request: dict[str, Any], timeout_s: float) -> Any:
    """Send ``request`` as one line and return the decoded reply line. OSError when the socket cannot
    be reached (FileNotFoundError: nobody made it) or closes without answering (ConnectionResetError);
    ValueError (json.JSONDecodeError) on a reply that is not JSON; :class:`OwnershipError` (a
    PermissionError) when the socket or the process serving it is another user's."""
    path = Path(path)
    check_socket_owner(path)  # OwnershipError (a PermissionError): another user's socket
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        sock.connect(str(path))
        check_server_peer(sock, path)
        sock.sendall((json.dumps(request) + "\n").encode())
        data = b""
        while not data.endswith(b"\n"):
            chunk = sock.recv(_MAX_CHUNK)
            if not chunk:
                break
            data += chunk
            if len(data) > MAX_REPLY_BYTES:
                raise ValueError(f"reply longer than {MAX_REPLY_BYTES} bytes")
    if not data:
        raise ConnectionResetError(0, "the server closed the connection without answering")
    return json.loads(data)


__all__ = [
    "JsonLineServer",
    "OwnershipError",
    "SocketPathError",
    "claim_socket_path",
    "json_depth",
    "request_json_line",
]
