"""Sending the drives' frames, with the injected frame faults applied on the way out.

Dropped frames never leave; delayed ones wait in a heap serviced by the bank's receive thread;
corrupted ones go out one byte short (a frame that passed the CAN CRC but does not match the
mapping: the only kind of corruption any master can detect).
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import threading
import time

import can

from sim_target.emulated.node import EmulatedDrive

log = logging.getLogger(__name__)


class FrameLink:
    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.send_lock = threading.Lock()
        self._delayed: list[tuple[float, int, can.Message]] = []
        self._delay_seq = itertools.count()
        self._batch: list[can.Message] | None = None  # collecting a SYNC's answer (begin_batch)
        self._send_batch = getattr(bus, "send_batch", None)  # the ipc bus: one fan-out pass
        self.sent = 0
        self.dropped = 0
        self.delayed = 0
        self.corrupted = 0

    def emit(
        self,
        drive: EmulatedDrive,
        cob_id: int,
        data: bytes,
        fd: bool = False,
        corrupt: bool = False,
        delay_s: float = 0.0,
    ) -> None:
        """A frame from ``drive``, through its fault policy."""
        faults = drive.policy.faults
        if faults.active:
            rng = drive.policy.rng
            if faults.drop_probability and rng.random() < faults.drop_probability:
                self.dropped += 1
                return
            if faults.corrupt_probability and rng.random() < faults.corrupt_probability:
                corrupt = True
            delay_s = max(delay_s, faults.delay_s)
        if corrupt and data:
            data = data[:-1]
            self.corrupted += 1
        msg = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False, is_fd=fd, bitrate_switch=fd)
        if delay_s > 0:
            self.delayed += 1
            heapq.heappush(self._delayed, (time.monotonic() + delay_s, next(self._delay_seq), msg))
            return
        self.send(msg)

    def begin_batch(self) -> None:
        """Collect the frames sent from now until :meth:`flush` (a SYNC's TPDOs): sent in one call
        where the bus offers ``send_batch``, saving a pass through python-can per frame."""
        self._batch = []

    def flush(self) -> None:
        batch, self._batch = self._batch, None
        if not batch:
            return
        if self._send_batch is None or len(batch) == 1:
            for msg in batch:
                self.send(msg)
            return
        try:
            with self.send_lock:
                self._send_batch(batch)
        except (can.CanError, OSError) as exc:
            log.warning("emulated drives: sending %d frames failed: %s", len(batch), exc)
            return
        self.sent += len(batch)

    def send(self, msg: can.Message) -> None:
        if self._batch is not None:
            self._batch.append(msg)
            return
        try:
            with self.send_lock:
                self.bus.send(msg)
        except (can.CanError, OSError) as exc:
            log.warning("emulated drives: send 0x%03X failed: %s", msg.arbitration_id, exc)
            return
        self.sent += 1

    def next_due(self) -> float:
        return self._delayed[0][0] if self._delayed else math.inf

    def release_due(self, now: float) -> None:
        """Send the delayed frames whose time has come."""
        while self._delayed and self._delayed[0][0] <= now:
            _, _, msg = heapq.heappop(self._delayed)
            self.send(msg)
