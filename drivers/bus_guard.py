"""The master's watch for a second sender and a second master on its bus (docs/security.md, "A
second sender, a second master").

CAN has one sender per identifier and one NMT master per network. Every received frame passes
:meth:`BusGuard.watch` (the network's ``watch`` hook, before any service sees it):

- **A frame only a master sends** (NMT 0x000, SYNC 0x080, our master heartbeat 0x700 + our node
  id, an RPDO or an SDO request to one of our drives) comes from another master: we never receive
  our own frames. At start-up (:meth:`BusGuard.check_no_master`, before our first NMT command) it
  refuses the bus, :class:`MasterPresentError`, exit 2; later it is a :class:`BusIntruderError`.
- **A second sender of a drive's frame** (TPDO, heartbeat, EMCY):
  - a transport that says who sent each frame (the ipc bus: ``msg.sender``, one per connection,
    from SO_PEERCRED) names a sender other than the first one seen for that drive (its boot-up
    message, at start-up);
  - a drive answers each SYNC with one frame per TPDO: more TPDOs of one identifier than SYNCs
    sent since the guard was armed means someone else answers too (a forger that answers each
    SYNC is caught by the second cycle);
  - heartbeats come once per producer period: more than 1.5 × ``window`` in the last ``window``
    periods means two producers.

Each trip queues one :class:`BusIntruderError` (a :class:`~drivers.errors.TransportError`, so the
bus quick-stops the drives and the runtime faults) on the network's error queue; the caller's next
cycle raises it.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable, Iterable, Sequence

import can

from drivers.cia402 import frames as fr
from drivers.config import DriveBusConfig
from drivers.errors import TransportError
from drivers.network import DriveNetwork

SDO_REQUEST_BASE = 0x600
HEARTBEAT_WINDOW_PERIODS = 20  # the heartbeat rate is judged over this many producer periods
HEARTBEAT_SLACK = HEARTBEAT_WINDOW_PERIODS // 2  # extra beats tolerated (a producer catching up after a stall)
_BOOT_UP = fr.encode_heartbeat(fr.NmtState.BOOT_UP)
MAX_TPDO_CREDIT = 16  # SYNCs left unanswered (lost TPDOs) that later frames may still make up


class BusIntruderError(TransportError):
    """A second sender of a drive's identifier, or a second master, on the bus: FAULT (exit 3)."""

    fault_kind = "bus_intruder"


class MasterPresentError(BusIntruderError):
    """At start-up the bus already has a master: refused before sending anything (exit 2)."""

    exit_code = 2


class BusGuard:
    """Watches every received frame for a second sender or a second master (see module doc)."""

    def __init__(
        self,
        network: DriveNetwork,
        node_ids: Sequence[int],
        master_node_id: int,
        tpdo_cob_ids: Iterable[int],
        heartbeat_period_s: float,
        syncs_sent: Callable[[], int],
    ) -> None:
        """``syncs_sent``: how many SYNCs the master has sent so far (counted before each goes out)."""
        self.network = network
        self._syncs_sent = syncs_sent
        self._syncs_at_arm = 0
        self.node_ids = tuple(node_ids)
        self._master_only = {fr.NMT_COB_ID: "an NMT command", fr.SYNC_COB_ID: "a SYNC"}
        self._master_only[fr.HEARTBEAT_BASE + master_node_id] = f"a heartbeat of master node {master_node_id}"
        for node_id in self.node_ids:
            self._master_only[fr.RPDO1_BASE + node_id] = f"an RPDO to drive {node_id}"
            self._master_only[SDO_REQUEST_BASE + node_id] = f"an SDO request to drive {node_id}"
        self._tpdo_frames = dict.fromkeys(tpdo_cob_ids, 0)
        self._heartbeats: dict[int, collections.deque[float]] = {
            fr.HEARTBEAT_BASE + n: collections.deque() for n in self.node_ids
        }
        self._drive_cob_ids = {*self._tpdo_frames, *self._heartbeats, *(fr.EMCY_BASE + n for n in self.node_ids)}
        self._heartbeat_window_s = HEARTBEAT_WINDOW_PERIODS * heartbeat_period_s
        self._senders: dict[int, object] = {}  # node id -> the first sender of its frames (transports that say)
        self.armed = False
        self.tripped: str | None = None  # what was seen, once
        self.foreign_master: str | None = None

    def forget_senders(self) -> None:
        """Before a (re)connect: the drives' boot-up messages name their senders again."""
        self._senders.clear()

    def arm(self) -> None:
        """Start counting TPDOs against SYNCs (before the first SYNC of a run)."""
        for cob_id in self._tpdo_frames:
            self._tpdo_frames[cob_id] = 0
        for beats in self._heartbeats.values():
            beats.clear()
        self._syncs_at_arm = self._syncs_sent()
        self.tripped = None
        self.armed = True

    def _trip(self, what: str) -> None:
        if self.tripped is None:
            self.tripped = what
            self.network.errors.append(BusIntruderError(what))

    def watch(self, msg: can.Message, now: float) -> None:
        """Under the receive lock, for every received frame, before dispatch."""
        if msg.is_extended_id or msg.is_error_frame or not msg.is_rx:
            return
        self._check(msg.arbitration_id, msg.data, getattr(msg, "sender", None), msg.timestamp)

    def watch_frame(self, cob_id: int, data: bytes, sender: object, now: float) -> None:
        """:meth:`watch` on the raw path (drivers/network.py): a standard data frame received from
        ``sender`` (no message made for it); the same rules."""
        self._check(cob_id, data, sender, 0.0)

    def _check(self, cob_id: int, data: bytes | bytearray | None, sender: object, timestamp: float) -> None:
        """``timestamp``: the transport's wall-clock stamp of the frame (0: none, now is used)."""
        what = self._master_only.get(cob_id)
        if what is not None:
            text = f"second master on the bus: received {what} (0x{cob_id:03X}){_from(sender)}"
            if self.foreign_master is None:
                self.foreign_master = text
            self._trip(text)
            return
        if cob_id not in self._drive_cob_ids:
            return
        if sender is not None:
            node_id = cob_id & 0x7F  # every frame of one drive comes from one sender
            if cob_id in self._heartbeats and data is not None and bytes(data) == _BOOT_UP:
                # A drive (re)booting is its sender from now on; once running, the heartbeat
                # consumer reports the reboot itself (DriveStateError), so a forged boot-up faults too.
                self._senders[node_id] = sender
            first = self._senders.setdefault(node_id, sender)
            # The same peer's frames carry the same Sender object: identity first (30 ns) spares the
            # dataclass __eq__ (1 µs) on every drive frame of a healthy bus.
            if sender is not first and sender != first:
                self._trip(
                    f"second sender of 0x{cob_id:03X} (drive {node_id}): {_describe(sender)} besides {_describe(first)}"
                )
                return
        if not self.armed:
            return
        count = self._tpdo_frames.get(cob_id)
        if count is not None:
            syncs = self._syncs_sent() - self._syncs_at_arm
            count = max(count, syncs - MAX_TPDO_CREDIT) + 1  # lost frames leave bounded credit
            self._tpdo_frames[cob_id] = count
            if count > syncs:
                self._trip(f"second sender of TPDO 0x{cob_id:03X}: {count} frames for {syncs} SYNC(s) sent")
            return
        beats = self._heartbeats.get(cob_id)
        if beats is not None:
            # When it was on the bus (the transport's wall-clock stamp), not when we got round to
            # it: beats queued during a stall of ours are not a burst of theirs.
            seen = timestamp if timestamp > 0 else time.time()
            beats.append(seen)
            while beats and seen - beats[0] > self._heartbeat_window_s:
                beats.popleft()
            if len(beats) > HEARTBEAT_WINDOW_PERIODS + HEARTBEAT_SLACK:
                self._trip(
                    f"second sender of heartbeat 0x{cob_id:03X}: {len(beats)} in "
                    f"{self._heartbeat_window_s:.3f} s ({HEARTBEAT_WINDOW_PERIODS} periods)"
                )

    def check_no_master(self, listen_s: float) -> None:
        """At start-up, before our first frame: listen ``listen_s`` for another master's frames
        (the network's receive thread runs); :class:`MasterPresentError` if any."""
        deadline = time.monotonic() + listen_s
        while time.monotonic() < deadline and self.foreign_master is None:
            time.sleep(0.002)
        if self.foreign_master is not None:
            # drop the queued run-time error: the refusal below is the one to report
            errors = self.network.errors
            keep = [e for e in errors if type(e) is not BusIntruderError]
            errors.clear()
            errors.extend(keep)
            raise MasterPresentError(f"{self.foreign_master}; not started (one master per bus)")


def master_listen_s(config: DriveBusConfig) -> float:
    """How long start-up listens for another master: three of our master-heartbeat periods (a
    master, idle or running, sends its heartbeat), at least five control periods (its SYNCs)."""
    return max(3 * config.master_heartbeat_ms / 1000, 5 * config.period_s)


def _describe(sender: object) -> str:
    pid, uid = getattr(sender, "pid", None), getattr(sender, "uid", None)
    return f"pid {pid} (uid {uid})" if pid is not None else str(sender)


def _from(sender: object) -> str:
    return f" from {_describe(sender)}" if sender is not None else ""


__all__ = ["BusGuard", "BusIntruderError", "MasterPresentError", "master_listen_s"]
