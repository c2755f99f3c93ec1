"""The answer to a SYNC: every drive's TPDO(s) with the published joint state in its own units.

Two paths, one content (the same bytes on the bus):

- the hot path, on a bus that sends a preallocated :class:`~drivers.ipc.frame.FrameBatch` (the
  ipc bus itself, not a wrapper): when every drive is NMT operational with the tagged CAN FD TPDO
  (0x2100 echoed) and no frame fault is pending on it, the six TPDOs are written into the one
  datagram made once by a single ``struct.pack_into`` over the whole datagram (the frames' headers
  rewritten with the values they were encoded with) and sent with one call: no message, no
  encoding, no per-drive call per SYNC;
- otherwise each drive's :func:`~sim_target.emulated.pdo.send_tpdos` through the
  :class:`~sim_target.emulated.link.FrameLink` (injected drops, delays, corruption; other layouts;
  other buses), collected into one ``send_batch``.

Scaling (counts, counts/s, per mille) in plain floats: for six joints several times cheaper than
numpy's per-call overhead; ``round`` rounds half to even as ``np.rint`` does.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Sequence

import can

from drivers.cia402 import frames as fr
from drivers.cia402.state_machine import (
    State,
)
from drivers.ipc.frame import FrameBatch
from sim_target.emulated import pdo
from sim_target.emulated.link import FrameLink
from sim_target.emulated.node import EmulatedDrive
from sim_target.emulated.p402 import WORD_ENABLED, WORD_LIMITED, statusword
from sim_target.emulated.rawbus import frame_sender

log = logging.getLogger(__name__)

INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1
INT16_MIN, INT16_MAX = -32768, 32767


Feedback = tuple[list[float], list[float], list[float]]  # position_rad, velocity_rad_s, torque_nm

# One FD frame of the batch holding a tagged FD TPDO: the SocketCAN header (can_id, len, flags, two
# reserved bytes; drivers/ipc/frame.py) then drivers.cia402.frames' "<HhiiB" and its padding (3 bytes
# to the FD length 16, 48 to the 64-byte data field). Unpacking the encoded header and packing it
# back gives the same bytes in either byte order, so one little-endian format covers the datagram.
_FRAME_FORMAT = "IBBBB" + "HhiiB51x"
_FIELDS_PER_FRAME = 10
_DATA_FIELD = 5  # the statusword's index within a frame's fields


def clip_int(value: float, low: int, high: int) -> int:
    """``value`` rounded half to even and clipped to [low, high]; a non-finite value clips too."""
    if value != value:  # NaN: no count to report; 0 rather than a crash on the bus thread
        return 0
    if value >= high:
        return high
    if value <= low:
        return low
    return round(value)


def scaled_feedback(
    drives: Sequence[EmulatedDrive], feedback: Feedback | None
) -> tuple[list[int], list[int], list[int]]:
    """The published state in each drive's units (counts, counts/s, ‰), all joints at once."""
    n = len(drives)
    if feedback is None:
        return [0] * n, [0] * n, [0] * n
    position, velocity, torque = feedback
    return (
        [clip_int(q * d.counts_per_rad, INT32_MIN, INT32_MAX) for d, q in zip(drives, position, strict=True)],
        [clip_int(v * d.counts_per_rad, INT32_MIN, INT32_MAX) for d, v in zip(drives, velocity, strict=True)],
        [
            clip_int(t * d.units_per_nm / d.rated_torque_mnm, INT16_MIN, INT16_MAX)
            for d, t in zip(drives, torque, strict=True)
        ],
    )


class SyncAnswer:
    """Sends the drives' answer to each SYNC (see the module doc)."""

    def __init__(self, link: FrameLink, drives: Sequence[EmulatedDrive], bus: can.BusABC) -> None:
        self._link = link
        self._drives = drives
        self._send_frames = frame_sender(bus)
        self._batch: FrameBatch | None = None
        self._struct: struct.Struct | None = None
        self._values: list[int] = []  # every field of the datagram, rewritten in place per SYNC
        if self._send_frames is not None:
            self._batch = FrameBatch(
                [
                    can.Message(
                        arbitration_id=fr.TPDO1_BASE + d.node_id,
                        data=bytearray(fr.TPDO_FD_SYNC_LENGTH),
                        is_extended_id=False,
                        is_fd=True,
                        bitrate_switch=True,
                    )
                    for d in drives
                ]
            )
            self._struct = struct.Struct("<" + _FRAME_FORMAT * len(drives))
            assert self._struct.size == len(self._batch.datagram)  # 72-byte FD frames, back to back
            self._values = list(self._struct.unpack_from(self._batch.datagram))
        self.fast = 0  # SYNCs answered on the hot path (tests, profiling)

    def send(self, feedback: Feedback | None, counter: int) -> None:
        """Every operational drive's TPDO(s) for ``feedback`` (None: zeros), echoing ``counter``."""
        drives = self._drives
        batch = self._batch
        if batch is not None and self._pack(feedback, counter):
            assert self._send_frames is not None  # set together with the batch
            link = self._link
            try:
                with link.send_lock:
                    self._send_frames(batch)
            except (can.CanError, OSError) as exc:
                log.warning("emulated drives: sending %d frames failed: %s", batch.count, exc)
                return
            link.sent += batch.count
            self.fast += 1
            return
        position, velocity, torque = scaled_feedback(drives, feedback)
        link = self._link
        link.begin_batch()
        try:
            for drive in drives:
                if drive.nmt is fr.NmtState.OPERATIONAL:
                    i = drive.index
                    pdo.send_tpdos(link, drive, position[i], velocity[i], torque[i], counter)
        finally:
            link.flush()

    def _pack(self, feedback: Feedback | None, counter: int) -> bool:
        """Write every drive's tagged FD TPDO into the batch; False (nothing to send from it) when
        a drive needs the slow path: not operational, another layout, a frame fault pending.
        Written out flat (no helper call per value in range) and packed with one call: it runs for
        every drive every period."""
        drives = self._drives
        operational = fr.NmtState.OPERATIONAL
        enabled = State.OPERATION_ENABLED
        values = self._values
        if feedback is None:
            zeros = [0.0] * len(drives)
            position, velocity, torque = zeros, zeros, zeros
        else:
            position, velocity, torque = feedback
        k = _DATA_FIELD
        for drive, q, v, t in zip(drives, position, velocity, torque, strict=True):
            policy = drive.policy
            if (
                drive.nmt is not operational
                or not drive.fd_sync_echo
                or not drive.tpdo1_valid
                or policy.drop_next
                or policy.corrupt_next
                or policy.delay_next
                or policy.faults.active
            ):
                return False
            if drive.state is enabled:
                values[k] = WORD_LIMITED if drive.limited else WORD_ENABLED
            else:
                values[k] = statusword(drive)
            cpr = drive.counts_per_rad
            # In range: round() as clip_int rounds; out of range or NaN: clip_int clips.
            permille = t * drive.units_per_nm / drive.rated_torque_mnm
            values[k + 1] = (
                round(permille) if INT16_MIN < permille < INT16_MAX else clip_int(permille, INT16_MIN, INT16_MAX)
            )
            counts = q * cpr
            values[k + 2] = round(counts) if INT32_MIN < counts < INT32_MAX else clip_int(counts, INT32_MIN, INT32_MAX)
            rate = v * cpr
            values[k + 3] = round(rate) if INT32_MIN < rate < INT32_MAX else clip_int(rate, INT32_MIN, INT32_MAX)
            values[k + 4] = counter
            k += _FIELDS_PER_FRAME
        assert self._batch is not None and self._struct is not None  # set together
        self._struct.pack_into(self._batch.datagram, 0, *values)
        return True
