"""The ipc bus's raw datagram API (drivers/ipc: ``send_frames``, ``recv_frames``), when the drives'
bus offers it as is: the emulated drives' hot path (no :class:`can.Message` per frame).

Only the :class:`~drivers.ipc.bus.IpcBus` itself qualifies: a wrapper (the capture bus, which must
see every frame through ``send``/``recv``), python-can's ``virtual`` bus, the bridge, and an ipc
bus with python-can receive filters keep python-can's ``send``/``recv`` (filters are applied only
there).
"""

from __future__ import annotations

from collections.abc import Callable

import can

from drivers.ipc.bus import IpcBus
from drivers.ipc.directory import Sender
from drivers.ipc.frame import FrameBatch

RawFrames = list[tuple[int, bytes, bool]]  # (can_id with SocketCAN's flags, data, is_fd)
FrameReceiver = Callable[[float | None], tuple[Sender | None, RawFrames] | None]
DatagramReceiver = Callable[[float | None], tuple[Sender | None, bytes] | None]


def frame_sender(bus: can.BusABC) -> Callable[[FrameBatch], None] | None:
    """``bus.send_frames`` when ``bus`` is the ipc bus itself, else None."""
    return bus.send_frames if type(bus) is IpcBus else None


def frame_receiver(bus: can.BusABC) -> FrameReceiver | None:
    """``bus.recv_frames`` when ``bus`` is the ipc bus itself with no receive filter, else None."""
    return bus.recv_frames if type(bus) is IpcBus and not bus.filters else None


def datagram_receiver(bus: can.BusABC) -> DatagramReceiver | None:
    """``bus.recv_datagram`` when ``bus`` is the ipc bus itself, CAN FD (every frame handed out),
    with no receive filter; else None."""
    if type(bus) is IpcBus and not bus.filters and bus.protocol is can.CanProtocol.CAN_FD:
        return bus.recv_datagram
    return None
