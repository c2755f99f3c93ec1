"""The emulated drives' receive side: one call per datagram or frame, three paths, one behaviour.

- the ipc bus with CAN FD (``recv_datagram``): a datagram as it came. A master's cycle (its RPDOs
  to these drives, then a SYNC) whose frame headers are those of the last cycle parsed the long
  way is read with one ``struct`` unpack (:class:`CycleLayout`): no list, tuple or slice per
  frame; anything else goes through :func:`~drivers.ipc.frame.raw_frames` frame by frame;
- the ipc bus with classical CAN (``recv_frames``): the datagram's frames undecoded;
- any other bus (virtual, the bridge, a capture wrapper, receive filters): python-can's ``recv``.

Every path applies the same checks and counts (sim_target/drives.py, ``_dispatch``).
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable, Sequence
from time import monotonic

import can

from drivers.cia402 import frames as fr
from drivers.ipc.directory import Sender
from drivers.ipc.frame import CAN_EFF_FLAG, CAN_EFF_MASK, CAN_ERR_FLAG, CAN_RTR_FLAG, FrameError, raw_frames
from sim_target.emulated.node import EmulatedDrive
from sim_target.emulated.rawbus import RawFrames

log = logging.getLogger(__name__)

_NOT_A_DATA_FRAME = CAN_EFF_FLAG | CAN_RTR_FLAG | CAN_ERR_FLAG
_unpack_rpdo = fr.RPDO_STRUCT.unpack
_HEADER = "IBBBB"  # SocketCAN's frame header: can_id, len, flags (classical: pad), two reserved bytes


class CycleLayout:
    """The frame headers of one master's cycle datagram (RPDOs to these drives, then a SYNC) and
    the two structs that read it: every header at once (compared whole with the learnt ones),
    every RPDO's controlword and target torque and the SYNC counter at once."""

    def __init__(self, frames: RawFrames, size: int, headers: tuple[int, ...], drives: list[EmulatedDrive]) -> None:
        header_format, data_format = "<", "<"
        for _can_id, data, is_fd in frames:
            room = 64 if is_fd else 8
            header_format += _HEADER + f"{room}x"
            fields = "Hh" if len(data) == fr.RPDO_LENGTH else "B" * len(data)  # an RPDO; the SYNC
            data_format += f"8x{fields}{room - len(data)}x"
        self.size = size
        self.headers = headers
        self.read_headers = struct.Struct(header_format).unpack
        self.read_data = struct.Struct(data_format).unpack
        self.drives = drives
        self.frames = len(frames)
        self.sync_counter = len(frames[-1][1]) == 1

    @staticmethod
    def learn(datagram: bytes, frames: RawFrames, rpdo_drive: dict[int, EmulatedDrive]) -> CycleLayout | None:
        """The layout of ``datagram`` (parsed into ``frames``) when it is a cycle: one or more
        RPDOs of these drives, well formed, then a SYNC of 0 or 1 byte; else None."""
        if len(frames) < 2 or frames[-1][0] != fr.SYNC_COB_ID or len(frames[-1][1]) > 1:
            return None
        drives = [rpdo_drive.get(can_id) for can_id, _data, _fd in frames[:-1]]
        if any(drive is None for drive in drives) or any(len(d) != fr.RPDO_LENGTH for _c, d, _f in frames[:-1]):
            return None
        header = struct.Struct("<" + _HEADER)
        headers: list[int] = []
        offset = 0
        for _can_id, _data, is_fd in frames:  # a batch: each frame's type is its FD flag (raw_frames)
            headers += header.unpack_from(datagram, offset)
            offset += 72 if is_fd else 16
        return CycleLayout(frames, len(datagram), tuple(headers), drives)  # type: ignore[arg-type]  # no None


class DatagramReception:
    """Mixed into :class:`sim_target.drives.EmulatedDrives` (which provides the fields and
    ``_dispatch``/``_on_sync``): receive and handle one datagram or frame."""

    _bus: can.BusABC
    _rpdo_drive: dict[int, EmulatedDrive]
    _received: int
    _malformed: int
    _recv_datagram: Callable[[float | None], tuple[Sender | None, bytes] | None] | None
    _recv_frames: Callable[[float | None], tuple[Sender | None, RawFrames] | None] | None
    _cycle: CycleLayout | None
    cycles_read: int  # cycle datagrams read by the layout (one unpack): tests, profiling

    def _dispatch(self, cob_id: int, data: bytes | bytearray) -> None:
        raise NotImplementedError

    def _on_sync(self, counter: int) -> None:
        raise NotImplementedError

    def _receive(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for one datagram (ipc) or frame and handle it; False if none."""
        if self._recv_datagram is not None:
            got = self._recv_datagram(timeout_s)
            if got is None:
                return False
            if not self._handle_cycle(got[1]):
                try:
                    frames = raw_frames(got[1])
                except FrameError:
                    self._malformed += 1  # not SocketCAN frames: nothing in it is the drives'
                    return True
                self._handle_frames(frames)
                self._cycle = CycleLayout.learn(got[1], frames, self._rpdo_drive) or self._cycle
            return True
        if self._recv_frames is not None:
            got_frames = self._recv_frames(timeout_s)
            if got_frames is None:
                return False
            self._handle_frames(got_frames[1])
            return True
        msg = self._bus.recv(timeout_s)
        if msg is None:
            return False
        self._handle(msg)
        return True

    def _handle_cycle(self, datagram: bytes) -> bool:
        """``datagram`` handled as the learnt cycle; False (nothing done) when it is not one."""
        cycle = self._cycle
        if cycle is None or len(datagram) != cycle.size or cycle.read_headers(datagram) != cycle.headers:
            return False
        values = cycle.read_data(datagram)
        self._received += cycle.frames
        self.cycles_read += 1
        operational = fr.NmtState.OPERATIONAL
        now = monotonic()
        i = 0
        for drive in cycle.drives:  # sim_target.emulated.pdo.on_rpdo, inlined
            if drive.nmt is operational and drive.rpdo_valid:  # else ignored (CiA 301)
                drive.controlword = values[i]
                drive.target_permille = values[i + 1]
                if drive.rpdo_timeout_ms:
                    drive.last_rpdo_s = now
            i += 2
        counter = values[i] if cycle.sync_counter else 0
        if cycle.sync_counter and not 1 <= counter <= 240:
            self._malformed += 1  # as _dispatch counts it
            return True
        try:
            self._on_sync(counter)
        except Exception:  # an emulator bug must not silence the drives
            log.exception("emulated drives: handling the SYNC failed")
        return True

    def _handle(self, msg: can.Message) -> None:
        """One frame from python-can's recv."""
        self._received += 1
        try:
            if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
                self._malformed += 1
                return
            self._dispatch(msg.arbitration_id, msg.data)
        except Exception:  # an emulator bug must not silence the drives
            log.exception("emulated drives: handling 0x%03X failed", msg.arbitration_id)

    def _handle_frames(self, frames: RawFrames) -> None:
        """A datagram's frames from the ipc bus, undecoded: the same checks as :meth:`_handle`.
        An RPDO is latched here (:func:`sim_target.emulated.pdo.on_rpdo` inlined), stamped with
        the datagram's arrival for the RPDO watch."""
        rpdo_drive = self._rpdo_drive
        operational = fr.NmtState.OPERATIONAL
        now = monotonic()
        for can_id, data, _is_fd in frames:
            self._received += 1
            try:
                drive = rpdo_drive.get(can_id)
                if drive is not None:
                    if drive.nmt is not operational or not drive.rpdo_valid:
                        continue  # PDOs are ignored outside NMT operational (CiA 301)
                    if len(data) != fr.RPDO_LENGTH:
                        self._malformed += 1
                        continue
                    drive.controlword, drive.target_permille = _unpack_rpdo(data)
                    if drive.rpdo_timeout_ms:
                        drive.last_rpdo_s = now
                    continue
                if can_id & _NOT_A_DATA_FRAME:  # error, remote or extended: none is the drives'
                    self._malformed += 1
                    continue
                self._dispatch(can_id, data)
            except Exception:  # an emulator bug must not silence the drives
                log.exception("emulated drives: handling 0x%03X failed", can_id & CAN_EFF_MASK)


def rpdo_drives(drives: Sequence[EmulatedDrive]) -> dict[int, EmulatedDrive]:
    """RPDO1's COB-ID of each drive -> the drive."""
    return {fr.RPDO1_BASE + drive.node_id: drive for drive in drives}
