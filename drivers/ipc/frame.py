"""SocketCAN's frame layout, as pure functions: one datagram of the ipc bus is one frame.

Classical frames are Linux's ``struct can_frame`` (16 bytes), CAN FD frames its ``struct
canfd_frame`` (72 bytes), both in host byte order as a CAN_RAW socket reads them::

    struct can_frame   { u32 can_id; u8 len; u8 __pad; u8 __res0; u8 len8_dlc; u8 data[8];  }
    struct canfd_frame { u32 can_id; u8 len; u8 flags; u8 __res0; u8 __res1; u8 data[64]; }

``can_id`` carries the identifier (11 or 29 bits) and three flags: CAN_EFF_FLAG (extended id),
CAN_RTR_FLAG (remote request), CAN_ERR_FLAG (error frame; the identifier is then the error class,
linux/can/error.h). The datagram's length tells the two layouts apart, as CAN_MTU and CANFD_MTU do
on a SocketCAN socket. A datagram of any other length is a batch (:func:`split_batch`): frames back
to back, each 72 bytes when its byte 5 carries CANFD_FDF (always set on FD frames here), else 16;
no batch has the length of one frame. See docs/ipc_bus.md.
"""

from __future__ import annotations

import struct

import can

CAN_EFF_FLAG = 0x80000000
CAN_RTR_FLAG = 0x40000000
CAN_ERR_FLAG = 0x20000000
CAN_EFF_MASK = 0x1FFFFFFF
CAN_SFF_MASK = 0x000007FF

CANFD_BRS = 0x01  # bit rate switch
CANFD_ESI = 0x02  # error state indicator of the sender
CANFD_FDF = 0x04  # set on every FD frame (Linux >= 5.14 marks them so)

CAN_MTU = 16
CANFD_MTU = 72
CAN_MAX_DLEN = 8
CANFD_MAX_DLEN = 64
CANFD_LENGTHS = frozenset({0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64})

# A batch (send_batch: one control cycle's frames) is one datagram of at most this many frames.
MAX_BATCH_FRAMES = 64
MAX_DATAGRAM = MAX_BATCH_FRAMES * 72

# linux/can/error.h: a controller problem, byte 1 says which; RX overflow is what a slow reader sees.
CAN_ERR_CRTL = 0x00000004
CAN_ERR_CRTL_RX_OVERFLOW = 0x01
CAN_ERR_DLC = 8

# The smallest CAN FD length that holds n bytes, n = 0..64.
_FD_LENGTH = tuple(min(length for length in CANFD_LENGTHS if length >= n) for n in range(CANFD_MAX_DLEN + 1))

_CAN_FRAME = struct.Struct("=IBBBB8s")
_CANFD_FRAME = struct.Struct("=IBBBB64s")


class FrameError(ValueError):
    """A datagram that is not a SocketCAN frame, or a message that cannot become one."""


def _can_id(msg: can.Message) -> int:
    can_id = msg.arbitration_id
    if msg.is_error_frame:
        return CAN_ERR_FLAG | (can_id & CAN_EFF_MASK)
    if msg.is_extended_id:
        if can_id > CAN_EFF_MASK:
            raise FrameError(f"extended id 0x{can_id:X} exceeds 29 bits")
        can_id |= CAN_EFF_FLAG
    elif can_id > CAN_SFF_MASK:
        raise FrameError(f"standard id 0x{can_id:X} exceeds 11 bits")
    if msg.is_remote_frame:
        can_id |= CAN_RTR_FLAG
    return can_id


def encode(msg: can.Message) -> bytes:
    """The SocketCAN bytes of ``msg``: 16 bytes for a classical frame, 72 for CAN FD."""
    can_id = _can_id(msg)
    length = msg.dlc
    data = bytes(msg.data) if msg.data else b""
    if msg.is_fd:
        if length > CANFD_MAX_DLEN or len(data) > CANFD_MAX_DLEN:
            raise FrameError(f"CAN FD frame 0x{msg.arbitration_id:X}: {max(length, len(data))} bytes (max 64)")
        length = _FD_LENGTH[max(length, len(data))]  # padded up to a CAN FD length, as SocketCAN does
        flags = CANFD_FDF | (CANFD_BRS if msg.bitrate_switch else 0) | (CANFD_ESI if msg.error_state_indicator else 0)
        return _CANFD_FRAME.pack(can_id, length, flags, 0, 0, data)
    if length > CAN_MAX_DLEN or len(data) > CAN_MAX_DLEN:
        raise FrameError(f"classical frame 0x{msg.arbitration_id:X}: {max(length, len(data))} bytes (max 8)")
    return _CAN_FRAME.pack(can_id, length, 0, 0, 0, data)


def decode(
    frame: bytes,
    channel: str | None = None,
    timestamp: float = 0.0,
    is_rx: bool = True,
    message_type: type[can.Message] = can.Message,
) -> can.Message:
    """A :class:`can.Message` (or ``message_type``) from SocketCAN bytes; :class:`FrameError` if
    they are not a frame."""
    size = len(frame)
    if size == CAN_MTU:
        can_id, length, _pad, _res0, _len8_dlc, payload = _CAN_FRAME.unpack(frame)
        is_fd = False
        flags = 0
        if length > CAN_MAX_DLEN:
            raise FrameError(f"classical frame with length {length}")
    elif size == CANFD_MTU:
        can_id, length, flags, _res0, _res1, payload = _CANFD_FRAME.unpack(frame)
        is_fd = True
        if length not in CANFD_LENGTHS:
            raise FrameError(f"CAN FD frame with length {length}")
    else:
        raise FrameError(f"datagram of {size} bytes is neither a CAN ({CAN_MTU}) nor a CAN FD ({CANFD_MTU}) frame")
    remote = bool(can_id & CAN_RTR_FLAG)
    return message_type(
        timestamp=timestamp,
        arbitration_id=can_id & CAN_EFF_MASK,
        is_extended_id=bool(can_id & CAN_EFF_FLAG),
        is_remote_frame=remote,
        is_error_frame=bool(can_id & CAN_ERR_FLAG),
        dlc=length,
        data=None if remote else payload[:length],
        is_fd=is_fd,
        bitrate_switch=bool(flags & CANFD_BRS),
        error_state_indicator=bool(flags & CANFD_ESI),
        channel=channel,
        is_rx=is_rx,
    )


def rx_overflow_frame() -> bytes:
    """The error frame a SocketCAN controller reports after losing received frames."""
    data = bytes([0, CAN_ERR_CRTL_RX_OVERFLOW, 0, 0, 0, 0, 0, 0])
    return _CAN_FRAME.pack(CAN_ERR_FLAG | CAN_ERR_CRTL, CAN_ERR_DLC, 0, 0, 0, data)


_HEADER = struct.Struct("=IBB")  # can_id, len, flags (the FD layout's; classical frames: the pad byte)
_DATA_OFFSET = 8


def raw_frames(datagram: bytes) -> list[tuple[int, bytes, bool]]:
    """Each frame of a datagram (one frame or a batch) as ``(can_id, data, is_fd)``, undecoded:
    ``can_id`` with SocketCAN's flags (CAN_EFF_FLAG...), ``data`` its ``len`` bytes. The hot
    path's parse (no :class:`can.Message`); :class:`FrameError` as :func:`decode` and
    :func:`split_batch` raise it."""
    size = len(datagram)
    frames = []
    offset = 0
    while offset < size:
        if size - offset < CAN_MTU:
            raise FrameError(f"datagram of {size} bytes: {size - offset} trailing bytes are not a frame")
        can_id, length, flags = _HEADER.unpack_from(datagram, offset)
        # One frame: its size says which layout; in a batch, the FD flag does (split_batch).
        is_fd = size == CANFD_MTU if size in (CAN_MTU, CANFD_MTU) else bool(flags & CANFD_FDF)
        mtu = CANFD_MTU if is_fd else CAN_MTU
        if offset + mtu > size:
            raise FrameError(f"batch of {size} bytes: the frame at byte {offset} is cut short")
        if length not in CANFD_LENGTHS if is_fd else length > CAN_MAX_DLEN:
            raise FrameError(f"{'CAN FD' if is_fd else 'classical'} frame with length {length}")
        start = offset + _DATA_OFFSET
        frames.append((can_id, datagram[start : start + length], is_fd))
        offset += mtu
    return frames


class FrameBatch:
    """A fixed list of frames encoded once into one preallocated datagram (a control cycle's
    frames): each cycle rewrites the payloads in place (:attr:`payloads`, writable views into
    the datagram, e.g. for ``struct.pack_into``) and sends :attr:`datagram` as it is, so nothing
    is allocated or encoded twice. The identifiers and lengths are fixed at construction."""

    def __init__(self, msgs: list[can.Message] | tuple[can.Message, ...]) -> None:
        if not 1 <= len(msgs) <= MAX_BATCH_FRAMES:
            raise FrameError(f"a batch holds 1 to {MAX_BATCH_FRAMES} frames, not {len(msgs)}")
        frames = [encode(msg) for msg in msgs]
        self.datagram = bytearray(b"".join(frames))
        self.count = len(frames)
        self.fd = any(msg.is_fd for msg in msgs)
        view = memoryview(self.datagram)
        self.payloads: list[memoryview] = []
        offset = 0
        for msg, frame in zip(msgs, frames, strict=True):
            start = offset + _DATA_OFFSET
            self.payloads.append(view[start : start + len(msg.data)])
            offset += len(frame)


def split_batch(datagram: bytes) -> list[bytes]:
    """The frames of a batch datagram, in order (each then goes to :func:`decode`).
    :class:`FrameError` when the bytes do not split into whole frames."""
    frames = []
    size = len(datagram)
    offset = 0
    while offset < size:
        if size - offset < CAN_MTU:
            raise FrameError(f"batch of {size} bytes: {size - offset} trailing bytes are not a frame")
        length = CANFD_MTU if datagram[offset + 5] & CANFD_FDF else CAN_MTU
        if offset + length > size:
            raise FrameError(f"batch of {size} bytes: the frame at byte {offset} is cut short")
        frames.append(datagram[offset : offset + length])
        offset += length
    return frames
