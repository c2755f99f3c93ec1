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

log = logging.getLogger(__name__)

RX_POLL_S = 0.005  # background receive (start-up, SDO): longest blocking wait
IDLE_POLL_S = 0.01  # cyclic mode: the background thread looks this often whether the caller is idle
IDLE_TAKEOVER_S = 0.02  # no cycle for this long: the background thread drains the bus

Handler = Callable[[Any, can.Message, float], None]  # (node record, frame, time.monotonic())


class DriveNetwork:
    """One python-can bus shared by the master's services. Not a public API: DriveBus owns it."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.rx_lock = threading.Lock()  # held by whichever thread calls bus.recv
        self.tx_lock = threading.Lock()
        self.errors: collections.deque[DriveError] = collections.deque()
        self.handlers: dict[int, tuple[Handler, Any]] = {}
        # Periodic work, given time.monotonic(): ``supervise`` runs holding rx_lock after the
        # queue was drained (heartbeat consumer check); ``produce`` any time (the master's heartbeat).
        self.supervise: Callable[[float], None] | None = None
        self.produce: Callable[[float], None] | None = None
        # Sees every received frame first (drivers.bus_guard: a second sender or master).
        self.watch: Callable[[can.Message, float], None] | None = None
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

    # --- receiving -------------------------------------------------------------------------------

    def subscribe(self, cob_id: int, handler: Handler, node: Any) -> None:
        self.handlers[cob_id] = (handler, node)

    def dispatch(self, msg: can.Message, now: float) -> None:
        """Under rx_lock: hand one frame to its service."""
        self.frames_received += 1
        watch = self.watch
        if watch is not None:
            watch(msg, now)
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            self.malformed += 1
            return
        entry = self.handlers.get(msg.arbitration_id)
        if entry is None:
            self.unknown_cob_id += 1
            return
        handler, node = entry
        try:
            handler(node, msg, now)
        except (fr.MalformedFrameError, ValueError):
            self.malformed += 1
        except Exception as exc:  # keep receiving, report once
            log.exception("frame handler failed")
            self.errors.append(TransportError(f"frame handler failed: {exc!r}"))

    def recv(self, timeout_s: float) -> can.Message | None:
        """One frame or None after ``timeout_s``; any failure of the backend is a TransportError."""
        try:
            return self.bus.recv(timeout_s)
        except TransportError:
            raise
        except Exception as exc:  # any backend failure is a transport error
            raise TransportError(f"receiving failed: {exc}") from exc

    def drain(self) -> None:
        """Under rx_lock: handle every frame already queued, without waiting."""
        monotonic = time.monotonic
        recv = self.recv
        dispatch = self.dispatch
        while True:
            msg = recv(0.0)
            if msg is None:
                return
            dispatch(msg, monotonic())

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
