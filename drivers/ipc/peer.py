"""The ipc bus's per-connection record and its counters (drivers/ipc/bus.py)."""

from __future__ import annotations

import socket
from dataclasses import dataclass

from drivers.ipc.directory import Sender

__all__ = ["IpcBusStats"]


@dataclass
class IpcBusStats:
    """Counters of one bus instance (frames, not datagrams to each peer, unless noted)."""

    frames_sent: int = 0
    frames_received: int = 0
    frames_dropped: int = 0  # (frame, peer) pairs lost because that peer's queue was full
    fd_frames_ignored: int = 0  # CAN FD frames received on a classical bus
    malformed: int = 0  # datagrams that were not SocketCAN frames
    peers_joined: int = 0  # connections made or accepted, this bus's lifetime
    peers_left: int = 0
    stale_sockets_removed: int = 0
    peers_refused: int = 0  # connections from or to another user's process (SO_PEERCRED)


class _Peer:
    """One connection to another bus instance (or the loopback pair to ourselves)."""

    __slots__ = ("dropped", "fd", "overflowed", "sender", "sock")

    def __init__(self, sock: socket.socket, sender: Sender | None = None) -> None:
        self.sock = sock
        self.fd = sock.fileno()
        self.dropped = 0
        self.overflowed = False  # frames were lost: the RX-overflow error frame goes first next time
        self.sender = sender
