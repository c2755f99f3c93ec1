"""The master's side of the CAN bus: sending, receiving, dispatching frames to the services.

Like canopen's ``Network``: services subscribe a handler per COB-ID, every received frame goes to
its handler; malformed and unknown frames are counted, never raised. Errors found while
receiving (a frame handler's, a transport failure, a service's supervision) are queued and
raised by the caller's next check (:meth:`DriveNetwork.raise_pending`).

Who receives: inside a control cycle, the caller's thread (:mod:`drivers.pdo`), holding
:attr:`DriveNetwork.rx_lock`. Otherwise a background thread: blocking in ``recv`` during start-up
and SDO transfers (canopen's SDO client waits on it), and, once cycles run, draining the bus only
when the caller has not exchanged for ``IDLE_TAKEOVER_S`` (late frames, heartbeats, EMCY between
runs). The background thread also runs the periodic work (``supervise``: the heartbeat consumer
check, after draining; ``produce``: the master's heartbeat, at every wake-up) at least every
``IDLE_POLL_S``, so both go on while the caller is idle.

Every send holds :attr:`DriveNetwork.tx_lock` (the master's heartbeat goes out from the
background thread while a cycle may be sending).

The raw path (:attr:`DriveNetwork.raw`, a bus with the ipc bus's ``send_frames`` /
``recv_frames``): the cycle sends one preallocated :class:`~drivers.ipc.frame.FrameBatch` and
receives whole datagrams undecoded; a frame whose COB-ID has a data handler
(:meth:`DriveNetwork.subscribe_data`: the TPDOs) goes to it on its raw bytes, with the bus guard's
check (``watch_frame``) on its sender, and no :class:`can.Message` is made. Every other frame (a
heartbeat, an EMCY, an SDO answer, anything flagged) becomes a message and takes
:meth:`DriveNetwork.dispatch` as before. Other buses (python-can's, the bridge, a capture
wrapper) keep the message path; the handlers and the guard's rule are the same on both.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import can

from drivers.cia402 import frames as fr
from drivers.errors import DriveError, TransportError
from drivers.ipc.directory import IpcMessage
from drivers.ipc.frame import CAN_EFF_FLAG, CAN_EFF_MASK, CAN_ERR_FLAG, CAN_RTR_FLAG, FrameBatch

log = logging.getLogger(__name__)

RX_POLL_S = 0.005  # background receive (start-up, SDO): longest blocking wait
IDLE_POLL_S = 0.01  # cyclic mode: the background thread looks this often whether the caller is idle
IDLE_TAKEOVER_S = 0.02  # no cycle for this long: the background thread drains the bus

Handler = Callable[[Any, can.Message, float], None]  # (node record, frame, time.monotonic())
DataHandler = Callable[[Any, bytes, float], None]  # (node record, the frame's data, time.monotonic())
# (COB-ID, data, sender or None, time.monotonic()): the guard's check of a standard data frame
FrameWatch = Callable[[int, bytes, Any, float], None]
RawFrame = tuple[int, bytes, bool]  # the ipc bus's undecoded frame: (can_id with flags, data, is_fd)


class DriveNetwork:
    """One python-can bus shared by the master's services. Not a public API: DriveBus owns it."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.rx_lock = threading.Lock()  # held by whichever thread calls bus.recv
        self.tx_lock = threading.Lock()
        self.errors: collections.deque[DriveError] = collections.deque()
        self.handlers: dict[int, tuple[Handler, Any]] = {}
        self.data_handlers: dict[int, tuple[DataHandler, Any]] = {}  # services that read data alone
        # Periodic work, given time.monotonic(): ``supervise`` runs holding rx_lock after the
        # queue was drained (heartbeat consumer check); ``produce`` any time (the master's heartbeat).
        self.supervise: Callable[[float], None] | None = None
        self.produce: Callable[[float], None] | None = None
        # Sees every received frame first (drivers.bus_guard: a second sender or master).
        self.watch: Callable[[can.Message, float], None] | None = None
        self.watch_frame: FrameWatch | None = None  # the same check on the raw path (no message)
        self.caller_receives = False  # True once cycles run: they receive on the caller's thread
        self.last_cycle_end_s = 0.0
        self.frames_sent = 0
        self.frames_received = 0
        self.malformed = 0
        self.unknown_cob_id = 0
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # --- sending ---------------------------------------------------------------------------------

    def send(self, msg: can.Message) -> None:
        try:
            with self.tx_lock:
                self.bus.send(msg)
        except TransportError:
            raise
        except (can.CanError, OSError) as exc:
            raise TransportError(f"sending 0x{msg.arbitration_id:03X} failed: {exc}") from exc
        self.frames_sent += 1

    def send_batch(self, msgs: Sequence[can.Message]) -> None:
        """Frames back to back: one batch where the transport has one (the bridge)."""
        bus = self.bus
        try:
            with self.tx_lock:
                send_batch = getattr(bus, "send_batch", None)
                if send_batch is not None:
                    send_batch(msgs)
                else:
                    send = bus.send
                    for msg in msgs:
                        send(msg)
        except TransportError:
            raise
        except (can.CanError, OSError) as exc:
            raise TransportError(f"sending the cycle's frames failed: {exc}") from exc
        self.frames_sent += len(msgs)

    def send_frames(self, batch: FrameBatch) -> None:
        """A preallocated batch as it is (the raw path, :attr:`raw`): one datagram, no encoding."""
        try:
            with self.tx_lock:
                self.bus.send_frames(batch)  # type: ignore[attr-defined]  # raw buses only (self.raw)
        except TransportError:
            raise
        except (can.CanError, OSError) as exc:
            raise TransportError(f"sending the cycle's frames failed: {exc}") from exc
        self.frames_sent += batch.count

    @property
    def raw(self) -> bool:
        """Does the bus take preallocated batches and hand out undecoded datagrams (the ipc bus)?"""
        bus = self.bus
        return hasattr(bus, "send_frames") and hasattr(bus, "recv_frames")

    # --- receiving -------------------------------------------------------------------------------

    def subscribe(self, cob_id: int, handler: Handler, node: Any) -> None:
        self.handlers[cob_id] = (handler, node)

    def subscribe_data(self, cob_id: int, handler: DataHandler, node: Any) -> None:
        """A handler that reads only the frame's data: on the raw path no message is made for it."""
        self.data_handlers[cob_id] = (handler, node)

    def dispatch(self, msg: can.Message, now: float) -> None:
        """Under rx_lock: hand one frame to its service."""
        self.frames_received += 1
        watch = self.watch
        if watch is not None:
            watch(msg, now)
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            self.malformed += 1
            return
        cob_id = msg.arbitration_id
        data_entry = self.data_handlers.get(cob_id)
        if data_entry is not None:
            self._handle(data_entry[0], data_entry[1], msg.data, now)
            return
        entry = self.handlers.get(cob_id)
        if entry is None:
            self.unknown_cob_id += 1
            return
        self._handle(entry[0], entry[1], msg, now)

    def dispatch_frames(self, sender: Any, frames: list[RawFrame], now: float) -> None:
        """Under rx_lock: one datagram's frames (the raw path). A standard data frame with a data
        handler goes to it on its bytes after the guard's check; any other frame as a message."""
        data_handlers = self.data_handlers
        watch_frame = self.watch_frame
        for can_id, data, is_fd in frames:
            entry = data_handlers.get(can_id)  # any flag set (extended, remote, error): no entry
            if entry is None:
                self.dispatch(_message(can_id, data, is_fd, sender), now)
                continue
            self.frames_received += 1
            if watch_frame is not None:
                watch_frame(can_id, data, sender, now)
            self._handle(entry[0], entry[1], data, now)

    def _handle(self, handler: Callable[[Any, Any, float], None], node: Any, frame: Any, now: float) -> None:
        try:
            handler(node, frame, now)
        except (fr.MalformedFrameError, ValueError):
            self.malformed += 1
        except Exception as exc:  # keep receiving, report once
            log.exception("frame handler failed")
            self.errors.append(TransportError(f"frame handler failed: {exc!r}"))

    def recv_frames(self, timeout_s: float) -> tuple[Any, list[RawFrame]] | None:
        """The raw path's receive: the next datagram's (sender, frames) or None after ``timeout_s``."""
        try:
            got: tuple[Any, list[RawFrame]] | None = self.bus.recv_frames(timeout_s)  # type: ignore[attr-defined]  # raw buses only
            return got
        except TransportError:
            raise
        except Exception as exc:  # any backend failure is a transport error
            raise TransportError(f"receiving failed: {exc}") from exc

    def recv(self, timeout_s: float) -> can.Message | None:
        """One frame or None after ``timeout_s``; any failure of the backend is a TransportError."""
        try:
            return self.bus.recv(timeout_s)
        except TransportError:
            raise
        except Exception as exc:  # any backend failure is a transport error
            raise TransportError(f"receiving failed: {exc}") from exc

    def receive_one(self, timeout_s: float) -> bool:
        """Under rx_lock: wait up to ``timeout_s`` for the next datagram (the raw path) or frame and
        hand it to its service; False when none came."""
        if self.raw:
            got = self.recv_frames(timeout_s)
            if got is None:
                return False
            self.dispatch_frames(got[0], got[1], time.monotonic())
            return True
        msg = self.recv(timeout_s)
        if msg is None:
            return False
        self.dispatch(msg, time.monotonic())
        return True

    def drain(self) -> None:
        """Under rx_lock: handle every frame already queued, without waiting."""
        while self.receive_one(0.0):
            pass

    # --- background thread -----------------------------------------------------------------------

    @property
    def receiving(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="drive-bus-rx", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None

    @contextlib.contextmanager
    def background_receive(self) -> Iterator[None]:
        """The background thread receives (blocking) meanwhile: canopen's SDO client waits for
        responses it routes."""
        previous = self.caller_receives
        self.caller_receives = False
        self._wake.set()
        try:
            yield
        finally:
            self.caller_receives = previous
            self.last_cycle_end_s = time.monotonic()

    def _run(self) -> None:
        monotonic = time.monotonic
        next_tick = monotonic()
        while not self._stop.is_set():
            if self.caller_receives:
                # Cycles receive on the caller's thread; step in only when it has gone idle, and
                # never block in recv while holding the bus (the next cycle must not wait for us).
                self._wake.wait(IDLE_POLL_S)
                self._wake.clear()
                if self._stop.is_set():
                    return
                now = monotonic()
                self._periodic(self.produce, now)  # the master's heartbeat goes on during cycles too
                if not self.caller_receives or now - self.last_cycle_end_s < IDLE_TAKEOVER_S:
                    continue
                if not self.rx_lock.acquire(blocking=False):
                    continue
                try:
                    self.drain()
                    self._periodic(self.supervise, monotonic())
                except TransportError as exc:
                    if not self._stop.is_set():
                        self.errors.append(exc)
                    return
                finally:
                    self.rx_lock.release()
                continue
            with self.rx_lock:
                try:
                    msg = self.recv(RX_POLL_S)
                except TransportError as exc:
                    if not self._stop.is_set():
                        self.errors.append(exc)
                    return
                now = monotonic()
                if msg is not None:
                    self.dispatch(msg, now)
            if now >= next_tick:
                next_tick = now + RX_POLL_S
                with self.rx_lock:
                    self._periodic(self.supervise, now)
                self._periodic(self.produce, now)

    def _periodic(self, work: Callable[[float], None] | None, now: float) -> None:
        if work is None:
            return
        try:
            work(now)
        except DriveError as exc:
            if not self._stop.is_set():
                self.errors.append(exc)


def _message(can_id: int, data: bytes, is_fd: bool, sender: Any) -> can.Message:
    """A raw frame as the message the ipc bus's ``recv`` would have handed out (its sender, the
    wall-clock stamp of its arrival: the guard dates heartbeats by it)."""
    remote = bool(can_id & CAN_RTR_FLAG)
    msg = IpcMessage(
        timestamp=time.time(),
        arbitration_id=can_id & CAN_EFF_MASK,
        is_extended_id=bool(can_id & CAN_EFF_FLAG),
        is_remote_frame=remote,
        is_error_frame=bool(can_id & CAN_ERR_FLAG),
        dlc=len(data),
        data=None if remote else data,
        is_fd=is_fd,
    )
    msg.sender = sender
    return msg
