"""``interface="ipc"``: a virtual CAN bus shared by any number of processes on one machine.

No network, no kernel module, no hub process (measured: twice the round trip, docs/ipc_bus.md):
the bus is a directory. Every bus instance binds a Unix SOCK_SEQPACKET socket in it and connects
to every other instance's socket, so each frame goes straight from sender to receiver as one
datagram in SocketCAN's layout (:mod:`drivers.ipc.frame`).

    bus = can.Bus(interface="ipc", channel="/run/hil/can", fd=True)   # a directory, created if missing
    bus = can.Bus(interface="ipc", channel="hil")        # a name: $XDG_RUNTIME_DIR/hil-can/hil or /run/hil/can/hil

Only its owner joins: the directory must be the current user's (or, with ``group``, that
group's) and writable by no one else; every peer's ``SO_PEERCRED`` is checked on connect and
accept (refused: ``stats.peers_refused``). Each received frame carries its sender
(:class:`IpcMessage`, ``msg.sender``). docs/security.md, docs/ipc_bus.md ("Design", "Semantics").

Semantics as python-can's ``virtual`` and SocketCAN (one sender's frames in order; ``send`` never
blocks: a full peer loses the frame, counted, and gets SocketCAN's RX-overflow error frame). The
cycle's hot path: ``send_batch``/``send_frames`` (a preallocated
:class:`~drivers.ipc.frame.FrameBatch`) send a cycle's frames as one datagram per peer;
``recv_frames`` (frames undecoded) and ``recv_datagram`` (as it came) receive one. Linux only.
"""

from __future__ import annotations

import collections
import errno
import fcntl
import logging
import os
import secrets
import select
import socket
import stat
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can

from drivers.ipc.directory import IpcMessage, IpcPathError, Sender, bus_directory, remove_socket_if_ours
from drivers.ipc.frame import (
    CAN_MTU,
    CANFD_MTU,
    MAX_BATCH_FRAMES,
    MAX_DATAGRAM,
    FrameBatch,
    FrameError,
    decode,
    encode,
    raw_frames,
    rx_overflow_frame,
    split_batch,
)
from drivers.ipc.peer import IpcBusStats, _Peer
from drivers.ownership import OwnershipError, group_id, peer_allowed, peer_credentials, private_directory

if TYPE_CHECKING:
    from drivers.config import TransportConfig

log = logging.getLogger(__name__)

SOCKET_SUFFIX = ".sock"
MAX_PATH_BYTES = 107  # sun_path is 108 bytes with the terminating NUL
DEFAULT_QUEUE_BYTES = 1 << 20  # per peer pair: ~2700 FD frames queued before a slow reader loses some
_CONNECT_TIMEOUT_S = 1.0
_WAKE = b"\x00"  # one byte on the loopback pair: shutdown wakes a blocked reader


class IpcBus(can.BusABC):
    """A python-can bus over Unix SOCK_SEQPACKET sockets in a shared directory (see module doc)."""

    def __init__(
        self,
        channel: str | os.PathLike[str] = "hil",
        can_filters: can.typechecking.CanFilters | None = None,
        receive_own_messages: bool = False,
        fd: bool = False,
        queue_bytes: int = DEFAULT_QUEUE_BYTES,
        group: str | int | None = None,
        **kwargs: Any,
    ) -> None:
        """``channel``: the bus directory or a name (:func:`bus_directory`); ``queue_bytes``: kernel
        buffer per peer pair (SO_SNDBUF); ``group``: who else may join (None: this user only).
        Other python-can arguments (``bitrate``...) are accepted and ignored."""
        if not hasattr(socket, "SOCK_SEQPACKET") or not hasattr(select, "epoll"):
            raise can.CanInterfaceNotImplementedError("the ipc bus needs Linux (AF_UNIX SOCK_SEQPACKET, epoll)")
        self.channel = os.fspath(channel)
        self.directory = bus_directory(channel).absolute()
        self.channel_info = f"ipc bus {self.directory}"
        self.stats = IpcBusStats()
        try:
            self._group_gid = group_id(group)
        except KeyError:
            raise can.CanInitializationError(f"ipc bus: no such group {group!r}") from None
        self._next_peer = 0
        self._fd = bool(fd)
        self._can_protocol = can.CanProtocol.CAN_FD if fd else can.CanProtocol.CAN_20
        self._receive_own = bool(receive_own_messages)
        self._queue_bytes = int(queue_bytes)
        self._lock = threading.Lock()  # membership changes (accept, peer gone) from send or recv threads
        self._closed = False
        self._peers: dict[int, _Peer] = {}  # fd -> peer, the other bus instances
        self._targets: tuple[_Peer, ...] = ()  # who a frame goes to: a snapshot, swapped under _lock
        self._ready: list[_Peer] = []  # readable after the last epoll; only the receiving thread
        # Frames of a received batch not handed out yet (only the receiving thread).
        self._batched: collections.deque[tuple[_Peer, bytes]] = collections.deque()
        self._epoll = select.epoll()
        self._loop_tx, self._loop_rx = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._loop_tx.setblocking(False)
        self._loop_rx.setblocking(False)
        self._loop = _Peer(self._loop_rx, Sender(0, os.getpid(), os.geteuid()))
        self._loop_out = _Peer(self._loop_tx)
        self._epoll.register(self._loop.fd, select.EPOLLIN)
        self._listen: socket.socket | None = None
        self._path: Path | None = None
        self._inode: tuple[int, int] | None = None
        try:
            self._join()
        except BaseException:
            self._close_sockets()
            raise
        self._listen_fd = self._listen.fileno() if self._listen is not None else -1
        self._pending_joins = select.poll()  # a peer waiting in our listen backlog: accept before sending
        self._pending_joins.register(self._listen_fd, select.POLLIN)
        super().__init__(channel=self.channel, can_filters=can_filters, **kwargs)

    # --- joining and leaving ---------------------------------------------------------------------

    def _join(self) -> None:
        try:
            private_directory(self.directory, self._group_gid)
            dir_fd = os.open(self.directory, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
        except OwnershipError as exc:
            raise IpcPathError(f"ipc bus: {exc}") from exc
        except (NotADirectoryError, FileExistsError, PermissionError) as exc:
            raise IpcPathError(f"ipc bus: cannot use directory {self.directory}: {exc.strerror}") from exc
        except OSError as exc:
            raise can.CanInitializationError(f"ipc bus: cannot use directory {self.directory}: {exc.strerror}") from exc
        try:
            # One joiner at a time: each newcomer connects to everyone already listening, and is
            # seen by no one twice. Without the lock two newcomers could miss or double each other.
            fcntl.flock(dir_fd, fcntl.LOCK_EX)
            name = f"{os.getpid()}-{secrets.token_hex(4)}{SOCKET_SUFFIX}"
            path = self.directory / name
            if len(os.fsencode(path)) > MAX_PATH_BYTES:
                raise can.CanInitializationError(
                    f"ipc bus: socket path {path} is longer than {MAX_PATH_BYTES} bytes; use a shorter directory"
                )
            listen = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            try:
                listen.bind(os.fspath(path))
                os.chmod(path, 0o660 if self._group_gid is not None else 0o600)  # not the umask's 0755
                listen.listen(socket.SOMAXCONN)
                listen.setblocking(False)
            except OSError as exc:
                listen.close()
                raise can.CanInitializationError(f"ipc bus: cannot listen on {path}: {exc.strerror}") from exc
            self._listen, self._path = listen, path
            st = os.stat(path)
            self._inode = (st.st_dev, st.st_ino)
            self._epoll.register(listen.fileno(), select.EPOLLIN)
            for entry in os.scandir(dir_fd):
                if entry.name.endswith(SOCKET_SUFFIX) and entry.name != name:
                    self._connect(self.directory / entry.name)
            self._publish_targets()
        finally:
            os.close(dir_fd)  # releases the lock

    def _connect(self, path: Path) -> None:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        sock.settimeout(_CONNECT_TIMEOUT_S)  # a stopped (SIGSTOP) peer with a full backlog must not hang us
        try:
            sock.connect(os.fspath(path))
        except ConnectionRefusedError:
            sock.close()
            # Under the directory lock every live peer listens: refused means its owner is gone.
            try:
                if stat.S_ISSOCK(os.lstat(path).st_mode):
                    os.unlink(path)
                    self.stats.stale_sockets_removed += 1
            except FileNotFoundError:
                pass
            return
        except OSError as exc:  # FileNotFoundError: it left meanwhile; TimeoutError: a stopped peer
            sock.close()
            if not isinstance(exc, FileNotFoundError):
                log.warning("ipc bus: peer %s not joined: %s", path, exc)
            return
        self._add_peer(sock, f"listening at {path}")

    def _sender_of(self, sock: socket.socket, where: str) -> Sender | None:
        """The peer's identity, or None (and the socket closed) when it is another user's."""
        try:
            creds = peer_credentials(sock)
        except OSError as exc:
            sock.close()
            log.warning("ipc bus %s: no credentials for a peer %s: %s", self.directory, where, exc)
            return None
        if not peer_allowed(creds, self._group_gid):
            sock.close()
            self.stats.peers_refused += 1
            log.warning("ipc bus %s: refused a peer of uid %d (pid %d) %s", self.directory, creds.uid, creds.pid, where)
            return None
        self._next_peer += 1
        return Sender(self._next_peer, creds.pid, creds.uid)

    def _add_peer(self, sock: socket.socket, where: str) -> None:
        sender = self._sender_of(sock, where)
        if sender is None:
            return
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self._queue_bytes)
        except OSError:
            pass  # the default buffer still works
        sock.setblocking(False)
        peer = _Peer(sock, sender)
        self._peers[peer.fd] = peer
        self._epoll.register(peer.fd, select.EPOLLIN)
        self.stats.peers_joined += 1

    def _publish_targets(self) -> None:
        others = tuple(self._peers.values())
        self._targets = ((self._loop_out,) + others) if self._receive_own else others

    def _accept_pending(self) -> None:
        with self._lock:
            if self._closed or self._listen is None:
                return
            while True:
                try:
                    sock, _ = self._listen.accept()
                except (BlockingIOError, InterruptedError):
                    break
                except OSError as exc:
                    log.warning("ipc bus: accept failed: %s", exc)
                    break
                self._add_peer(sock, "connecting")
            self._publish_targets()

    def _drop_peer(self, peer: _Peer) -> None:
        with self._lock:
            if self._peers.pop(peer.fd, None) is None:
                return
            try:
                self._epoll.unregister(peer.fd)
            except (OSError, ValueError):
                pass
            peer.sock.close()
            self.stats.peers_left += 1
            self._publish_targets()
        if peer in self._ready:
            self._ready.remove(peer)

    @property
    def peer_count(self) -> int:
        """Other bus instances this one is connected to now (joins not yet accepted excluded)."""
        return len(self._peers)

    # --- sending ---------------------------------------------------------------------------------

    def _encode(self, msg: can.Message) -> bytes:
        if msg.is_fd and not self._fd:
            raise can.CanOperationError("ipc bus: CAN FD frame on a classical bus (open it with fd=True)")
        try:
            return encode(msg)
        except FrameError as exc:
            raise can.CanOperationError(f"ipc bus: {exc}") from exc

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Put ``msg`` on the bus; never blocks (``timeout`` is accepted and unused, see module doc)."""
        self.send_batch([msg])

    def send_batch(self, msgs: list[can.Message] | tuple[can.Message, ...]) -> None:
        """Send several frames in order as one datagram to each peer (:meth:`send_frames`), in
        chunks of ``MAX_BATCH_FRAMES``. A peer whose queue is full loses the whole batch."""
        for msg in msgs:
            self._encode(msg)  # python-can's errors for a frame that cannot go on this bus
        for first in range(0, len(msgs), MAX_BATCH_FRAMES):
            self.send_frames(FrameBatch(msgs[first : first + MAX_BATCH_FRAMES]))

    def send_frames(self, batch: FrameBatch) -> None:
        """Send a :class:`~drivers.ipc.frame.FrameBatch` as it is: one datagram to each peer, no
        encoding (the hot path's send; otherwise as :meth:`send_batch`)."""
        if self._closed:
            raise can.CanOperationError("ipc bus: the bus is shut down")
        if batch.fd and not self._fd:
            raise can.CanOperationError("ipc bus: CAN FD frame on a classical bus (open it with fd=True)")
        if self._pending_joins.poll(0):
            self._accept_pending()
        self._fan_out(batch.datagram, batch.count)
        self.stats.frames_sent += batch.count

    def _fan_out(self, frame: bytes | bytearray, count: int = 1) -> None:
        """``frame``: one frame's datagram, or a batch of ``count`` frames."""
        for peer in self._targets:
            if peer.overflowed and not self._notify_overflow(peer):
                peer.dropped += count
                self.stats.frames_dropped += count
                continue
            try:
                peer.sock.send(frame, socket.MSG_NOSIGNAL)
            except BlockingIOError:
                peer.dropped += count
                peer.overflowed = True
                self.stats.frames_dropped += count
            except OSError as exc:  # EPIPE, ECONNRESET: the peer exited; EBADF: dropped meanwhile
                if exc.errno not in (errno.EPIPE, errno.ECONNRESET, errno.EBADF, errno.ENOTCONN):
                    raise can.CanOperationError(f"ipc bus: send failed: {exc}") from exc
                if peer is not self._loop_out:
                    self._drop_peer(peer)

    def _notify_overflow(self, peer: _Peer) -> bool:
        try:
            peer.sock.send(rx_overflow_frame(), socket.MSG_NOSIGNAL)
        except OSError:
            return False
        peer.overflowed = False
        return True

    # --- receiving -------------------------------------------------------------------------------

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        batched = self._batched
        while True:
            while batched:  # a batch's frames first, in order: frames of one sender stay in order
                peer, data = batched.popleft()
                msg = self._message(peer, data)
                if msg is not None:
                    return msg, False
            got = self._next_datagram(deadline)
            if got is None:
                return None, False
            peer, data = got
            if len(data) != CAN_MTU and len(data) != CANFD_MTU:  # a batch: handed out from above
                try:
                    batched.extend((peer, frame) for frame in split_batch(data))
                except FrameError:
                    self.stats.malformed += 1
                continue
            msg = self._message(peer, data)
            if msg is not None:
                return msg, False

    def recv_frames(self, timeout: float | None = None) -> tuple[Sender | None, list[tuple[int, bytes, bool]]] | None:
        """The next datagram's frames, undecoded: ``(sender, [(can_id, data, is_fd), ...])``
        (:func:`drivers.ipc.frame.raw_frames`), or None when ``timeout`` passes first: what
        :meth:`recv` hands out one by one, in order, without ``can_filters`` or timestamps."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if self._batched:
                peer, data = self._batched.popleft()
            else:
                got = self._next_datagram(deadline)
                if got is None:
                    return None
                peer, data = got
            try:
                frames = raw_frames(data)
            except FrameError:
                self.stats.malformed += 1
                continue
            if not self._fd and any(is_fd for _, _, is_fd in frames):
                kept = [frame for frame in frames if not frame[2]]
                self.stats.fd_frames_ignored += len(frames) - len(kept)
                frames = kept
                if not frames:
                    continue
            self.stats.frames_received += len(frames)
            return peer.sender, frames

    def recv_datagram(self, timeout: float | None = None) -> tuple[Sender | None, bytes] | None:
        """The next datagram as it came (a frame or a batch: :func:`~drivers.ipc.frame.raw_frames`), or
        None after ``timeout``: for a CAN FD bus's reader that parses its cycle itself (and counts it)."""
        if self._batched:  # frames a recv() split from a batch and did not hand out yet
            return self._batched[0][0].sender, self._batched.popleft()[1]
        got = self._next_datagram(None if timeout is None else time.monotonic() + timeout)
        return None if got is None else (got[0].sender, got[1])

    def _next_datagram(self, deadline: float | None) -> tuple[_Peer, bytes] | None:
        """The next datagram (a frame or a batch) from any peer by ``deadline`` (monotonic; None: forever)."""
        ready = self._ready
        while True:
            while ready:
                peer = ready[0]
                try:
                    data = peer.sock.recv(MAX_DATAGRAM)
                except (BlockingIOError, InterruptedError):
                    ready.pop(0)
                    continue
                except OSError:
                    ready.pop(0)
                    self._drop_peer(peer)
                    continue
                if len(data) == len(_WAKE) and peer is self._loop:  # shutdown() wakes us
                    raise can.CanOperationError("ipc bus: the bus is shut down")
                ready.pop(0)  # read again only once epoll says so: no failed recv after each datagram
                if not data:  # EOF: the peer closed or died
                    self._drop_peer(peer)
                    continue
                return peer, data
            if self._closed:
                raise can.CanOperationError("ipc bus: the bus is shut down")
            if deadline is None:
                wait_s = -1.0
            else:
                wait_s = deadline - time.monotonic()
                if wait_s < 0:
                    wait_s = 0.0
            try:  # epoll's timeout is in whole ms, rounded up (a 1 kHz loop slipped periods): a
                # finite wait goes through select() on the epoll descriptor (µs), then epoll.
                fd = self._epoll.fileno()
                if wait_s > 0 and fd < 1024:  # select's FD_SETSIZE
                    if not select.select([fd], [], [], wait_s)[0] and deadline is not None:
                        return None  # nothing came before the deadline: no epoll call
                    wait_s = 0.0
                events = self._epoll.poll(wait_s)
            except InterruptedError:
                events = []
            except (OSError, ValueError) as exc:  # the epoll was closed by shutdown()
                raise can.CanOperationError("ipc bus: the bus is shut down") from exc
            for fd, _mask in events:
                if fd == self._listen_fd:
                    self._accept_pending()
                    continue
                found = self._peers.get(fd) or (self._loop if fd == self._loop.fd else None)
                if found is not None and found not in ready:
                    ready.append(found)
            if not ready and deadline is not None and time.monotonic() >= deadline:
                return None

    def _message(self, peer: _Peer, data: bytes) -> can.Message | None:
        """One frame's bytes as a message from ``peer``; None (counted) when it is not one to hand out."""
        if len(data) == CANFD_MTU and not self._fd:
            self.stats.fd_frames_ignored += 1
            return None
        try:
            msg = decode(data, self.channel, time.time(), peer is not self._loop, IpcMessage)
        except FrameError:
            self.stats.malformed += 1
            return None
        if isinstance(msg, IpcMessage):
            msg.sender = peer.sender
        self.stats.frames_received += 1
        return msg

    def fileno(self) -> int:
        """An epoll descriptor, readable when a frame (or a newcomer) is waiting: for select/asyncio."""
        return self._epoll.fileno()

    # --- shutdown ----------------------------------------------------------------------------------

    def shutdown(self) -> None:
        """Leave the bus: close every connection and remove our own socket file (only ours)."""
        if self._closed:
            return
        super().shutdown()
        with self._lock:
            self._closed = True
        try:
            self._loop_tx.send(_WAKE, socket.MSG_NOSIGNAL)  # a reader blocked in epoll returns
        except OSError:
            pass
        self._close_sockets()

    def _close_sockets(self) -> None:
        with self._lock:
            self._closed = True
            if self._listen is not None:
                self._listen.close()
                self._remove_own_socket()
            for peer in self._peers.values():
                peer.sock.close()
            self._peers.clear()
            self._targets = ()
        # The loopback pair and the epoll stay open until the object goes (a reader thread may be in them).

    def _remove_own_socket(self) -> None:
        if self._path is not None and self._inode is not None:
            remove_socket_if_ours(self._path, self._inode)
        self._path = None

    def __del__(self) -> None:
        super().__del__()
        for closable in ("_loop_tx", "_loop_rx", "_epoll"):
            obj = getattr(self, closable, None)
            if obj is not None:
                obj.close()


def open_bus(config: TransportConfig) -> IpcBus:
    """``drivers.transport.BACKENDS``'s row; a directory that cannot be used is bad input (exit 2)."""
    from drivers.errors import DriveConfigError

    try:
        return IpcBus(config.channel, fd=config.fd, group=config.group)
    except (IpcPathError, ValueError) as exc:  # a file, another user's; ValueError: an empty channel
        raise DriveConfigError(f"channel {config.channel!r}: {exc}") from None
