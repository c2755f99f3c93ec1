"""N emulated CiA 402 joint drives (cyclic synchronous torque) on one python-can bus.

They speak exactly the protocol of :mod:`drivers.cia402` (same codec, same EDS, same state-machine
table) so the runtime's driver cannot tell them from real drives. No pybullet, no hil_runtime: the
plant is reached only through the calls below, made by ``sim_target/server.py``.

API: the server's ``DriveBank`` (sim_target/drive_bank.py), served on the owner's thread
(``start(own_thread=False)`` then ``serve_until(deadline_s)``) or on a thread of their own
(``start()``); ``set_sync_handler(fn)``: ``fn()`` runs on every SYNC after the RPDO set-points are
latched and the state machines stepped, before the TPDOs go out. On the ipc bus itself the hot
path takes whole datagrams undecoded and answers each SYNC with one preallocated batch
(sim_target/emulated/rawbus.py, answer.py); any other bus, python-can's ``recv``/``send``.

Lock-step: the SYNC handler steps the plant one period and publishes its state, so each SYNC
advances physics by exactly one period and the TPDOs answering that SYNC carry the new state.
Free-running: the plant steps on its own clock and the handler publishes the latest state.

:class:`EmulatedDrives` is the composition of one module per service, mirroring ``drivers/``
(:mod:`sim_target.emulated`), over one :class:`~sim_target.emulated.node.EmulatedDrive` record per
drive: NMT with boot-up and heartbeat producer (0x1017); the object dictionary from the EDS behind
canopen's ``LocalNode`` SDO server (an independent canopen master can read and write objects);
PDOs (only the layouts of :mod:`drivers.cia402.od`: anything else is refused with SDO abort
0x06040041); the CiA 402 power state machine, 0x6072 torque limit, quick stop per 0x605A, EMCY on
fault and on fault reset; and the watch on the master: its heartbeat (0x1016), its RPDOs
(0x1400:05), its SYNC (0x2101), any silent too long quick-stops an enabled drive (0x6007), so the
arm stops when the controlling process dies.

Fault injection (``EmulatedDrivesConfig.frame_faults`` at start, :meth:`apply_fault` or the
one-shot helpers at run time) acts on the frames the drives send: dropped, delayed, or corrupted
(sent one byte short: a frame that passed the CAN CRC but does not match the mapping, the only
kind of corruption any master can detect).
"""

from __future__ import annotations

import logging
import random
import threading
import time
from collections.abc import Callable
from time import monotonic
from typing import Any

import can
import canopen
import numpy as np

from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx
from drivers.cia402.scaling import counts_per_rad_from_resolution
from drivers.cia402.state_machine import State
from drivers.eds_check import load_dictionary
from drivers.joint_bus import JointReadings
from sim_target.emulated import p402, pdo
from sim_target.emulated.answer import SyncAnswer
from sim_target.emulated.inject import OneShotFaults
from sim_target.emulated.link import FrameLink
from sim_target.emulated.nmt import NmtSlave
from sim_target.emulated.node import (
    DriveCounters,
    EmulatedDrive,
    EmulatedDrivesConfig,
    FaultPolicy,
    FrameFaults,
    MasterLoss,
)
from sim_target.emulated.objects import ObjectServer
from sim_target.emulated.rawbus import datagram_receiver, frame_receiver
from sim_target.emulated.reception import CycleLayout, DatagramReception, rpdo_drives
from sim_target.emulated.supervision import MasterWatch

__all__ = ["DriveCounters", "EmulatedDrives", "EmulatedDrivesConfig", "FrameFaults", "MasterLoss", "make_drive_bank"]

log = logging.getLogger(__name__)

_POLL_S = 0.01  # longest receive wait: heartbeats and delayed frames are serviced at least this often
_CHECK_PERIOD_S = 0.005  # the master watches are checked at least this often while frames flow
_DRAIN_MAX = 1000  # frames handled before a check gives up waiting for an empty queue
_ENABLED = State.OPERATION_ENABLED  # a module global: the enum's class attribute costs more per period


class _EmuNetwork(canopen.Network):
    """canopen Network with no notifier: LocalNode SDO answers go out through the drive bank."""

    def __init__(self, bank: EmulatedDrives) -> None:
        super().__init__(None)
        self._bank = bank

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._bank._emit_from_cob(can_id, bytes(data))


class EmulatedDrives(OneShotFaults, DatagramReception):
    """The drive bank. Thread model: one thread does everything (SYNC, SDO, NMT, heartbeats,
    delayed frames, the master watch): the bank's own receive thread (``start()``), or the owner's
    thread calling :meth:`serve_until` (``start(own_thread=False)``: the target server, whose
    physics then steps on that same thread); getters may be called from any thread."""

    def __init__(self, bus: can.BusABC, config: EmulatedDrivesConfig) -> None:
        self.config = config
        self._bus = bus
        self._sync_handler: Callable[[], None] | None = None
        self._feedback: tuple[list[float], list[float], list[float]] | None = None
        self.n_joints = len(config.node_ids)
        self._sync_counter = 0  # counter byte of the last SYNC (0: the SYNC carried none)
        self._link = FrameLink(bus)
        self._drives: list[EmulatedDrive] = []
        self._watch = MasterWatch(self._link, self._drives)
        self._nmt = NmtSlave(self._link, self._drives, lambda drive, comm_only: self._objects.reset(drive, comm_only))
        self._objects = ObjectServer(
            config.encoder_counts_per_rev,
            config.heartbeat_producer_ms,
            lambda: self._feedback,
            lambda: self._sync_counter,
            self._watch.configure,
            self._nmt.schedule,
        )
        eds = config.eds_path or odx.EDS_PATH
        self._network = _EmuNetwork(self)
        counts_per_rad = counts_per_rad_from_resolution(config.encoder_counts_per_rev)
        for index, node_id in enumerate(config.node_ids):
            profile = config.profiles[index] if config.profiles is not None else None
            if profile is None:
                od = odx.load_object_dictionary(node_id, eds)
            else:  # a vendor's dictionary: imported as is (it lacks the emulated drive's own objects)
                od = load_dictionary(profile.eds, node_id)
            node = canopen.LocalNode(node_id, od)
            # This bank runs NMT and heartbeats itself; canopen's NmtSlave would start a python-can
            # periodic task on 0x1017 writes.
            node._write_callbacks.remove(node.nmt.on_write)
            self._network.add_node(node)
            faults = config.frame_faults
            policy = FaultPolicy(faults, random.Random(faults.seed * 1000 + node_id))
            drive = EmulatedDrive(index, node_id, node, counts_per_rad, policy)
            if profile is not None:
                drive.profile = profile
                drive.counts_per_rad = profile.counts_per_rad
                drive.torque_unit_nm = profile.joint_nm_per_unit_permille
                drive.units_per_nm = 1.0 / profile.joint_nm_per_unit_permille
            self._objects.attach(drive)
            self._drives.append(drive)
            self._objects.reset(drive, communication_only=False)
        # cob-id -> (handler, drive); a handler returns False for a malformed frame.
        self._by_cob: dict[int, tuple[Callable[[EmulatedDrive, bytes | bytearray], bool | None], EmulatedDrive]] = {}
        self._rpdo_drive = rpdo_drives(self._drives)  # the raw paths' inlined reception
        for drive in self._drives:
            self._by_cob[fr.RPDO1_BASE + drive.node_id] = (pdo.on_rpdo, drive)
            self._by_cob[fr.SDO_RX_BASE + drive.node_id] = (self._on_sdo, drive)
        self._answer = SyncAnswer(self._link, self._drives, bus)
        # The ipc bus itself: whole datagrams, undecoded (no can.Message per frame); any other bus
        # (virtual, the bridge, a capture wrapper) and a filtered one: python-can's recv.
        self._recv_datagram = datagram_receiver(bus)
        self._recv_frames = frame_receiver(bus) if self._recv_datagram is None else None
        self._cycle: CycleLayout | None = None  # the master's cycle datagram, once seen
        self.cycles_read = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._booted = False
        self._sync_seen = False  # a SYNC was handled since serve_until began
        self._next_check_s = 0.0
        self._failed = False  # the bus went away: serve_until only sleeps
        self._received = 0
        self._malformed = 0
        self._unknown = 0
        self._syncs = 0

    # --- the server's interface ------------------------------------------------------------------

    def start(self, own_thread: bool = True) -> None:
        """Boot every drive (boot-up message, NMT pre-operational) and start receiving: on a thread
        of its own, or (``own_thread=False``) only when the owner calls :meth:`serve_until` on its
        thread (the target server: physics and drives then share one thread, no lock hand-off)."""
        if self._booted:
            return
        self._booted = True
        now = time.monotonic()
        for drive in self._drives:
            self._nmt.boot(drive, now)
        self._stop.clear()
        self._next_check_s = now
        if own_thread:
            self._thread = threading.Thread(target=self._run, name="emulated-drives", daemon=True)
            self._thread.start()

    def set_sync_handler(self, handler: Callable[[], None] | None) -> None:
        self._sync_handler = handler

    def commanded_torque_nm(self) -> np.ndarray:
        enabled = _ENABLED
        return np.array(
            [
                d.applied_permille * d.rated_torque_mnm * d.torque_unit_nm if d.state is enabled else 0.0
                for d in self._drives
            ]
        )

    def plant_inputs(self) -> tuple[list[float], list[bool]]:
        """:meth:`commanded_torque_nm` and :meth:`brake_engaged` as plain lists, in one pass: the
        physics step's inputs, every period (two numpy arrays of six cost more than the pass)."""
        enabled = _ENABLED
        torque_nm: list[float] = []
        braked: list[bool] = []
        for d in self._drives:
            if d.state is enabled:
                torque_nm.append(d.applied_permille * d.rated_torque_mnm * d.torque_unit_nm)
                braked.append(False)
            else:
                torque_nm.append(0.0)
                braked.append(True)
        return torque_nm, braked

    def operation_enabled(self) -> np.ndarray:
        enabled = _ENABLED
        return np.array([d.state is enabled for d in self._drives], dtype=bool)

    def brake_engaged(self) -> np.ndarray:
        return ~self.operation_enabled()

    def states(self) -> tuple[State, ...]:
        return tuple(d.state for d in self._drives)

    def nmt_states(self) -> tuple[fr.NmtState, ...]:
        return tuple(d.nmt for d in self._drives)

    @property
    def master_losses(self) -> tuple[MasterLoss, ...]:
        """Every reaction of a drive to a silent master, in order (see sim_target.emulated.supervision)."""
        return tuple(self._watch.events)

    def publish_feedback(self, state: JointReadings) -> None:
        """The joint state the TPDOs answering the current (inside the SYNC handler) or next SYNC
        carry. Sync TPDOs only ever go out on SYNC (CiA 301)."""
        self._feedback = (
            np.asarray(state.position_rad, dtype=np.float64).tolist(),
            np.asarray(state.velocity_rad_s, dtype=np.float64).tolist(),
            np.asarray(state.torque_nm, dtype=np.float64).tolist(),
        )

    def publish_floats(self, feedback: tuple[list[float], list[float], list[float]]) -> None:
        """:meth:`publish_feedback` for a state already in plain floats (position, velocity,
        torque; the plant's ``measured_floats``), kept as it is: the tuple must not change after."""
        self._feedback = feedback

    def apply_fault(self, fault: Any) -> None:
        """A ``sim_target.config`` FrameFault (kind "frames") or DriveFault (kind "drive_fault")."""
        kind = getattr(fault, "kind", None)
        if kind == "frames":
            faults = FrameFaults(fault.drop_probability, fault.delay_s, fault.corrupt_probability, fault.seed)
            targets = fault.node_ids
            for drive in self._drives:
                if targets is None or drive.node_id in targets:
                    drive.policy.faults = faults
                    drive.policy.rng = random.Random(faults.seed * 1000 + drive.node_id)
        elif kind == "drive_fault":
            self.inject_drive_fault(fault.node_id, fault.error_code)
        else:
            raise ValueError(f"not a drive fault: {fault!r}")

    def safe_stop(self) -> None:
        """Torque off, brakes on: every drive to Switch On Disabled (no EMCY, no frames)."""
        for drive in self._drives:
            if drive.state not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                drive.state = State.SWITCH_ON_DISABLED
            drive.applied_permille = 0
            drive.target_permille = 0

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._thread = None

    @property
    def counters(self) -> DriveCounters:
        link = self._link
        return DriveCounters(
            self._received,
            link.sent,
            self._malformed,
            self._unknown,
            self._syncs,
            link.dropped,
            link.delayed,
            link.corrupted,
            len(self._watch.events),
        )

    # --- receive thread --------------------------------------------------------------------------

    def _next_due(self) -> float:
        return min(self._nmt.next_due(), self._link.next_due())

    def _run(self) -> None:
        while not self._stop.is_set() and not self._failed:
            self.serve_until(time.monotonic() + _POLL_S)

    def serve_until(self, deadline_s: float, return_on_sync: bool = False) -> None:
        """Receive and handle frames (SYNC answered at once) until ``time.monotonic()`` reaches
        ``deadline_s``, on the calling thread; heartbeats, delayed frames and the master watch are
        serviced on the way. Returns at the deadline (or at once when stopped), or, with
        ``return_on_sync``, after the first SYNC handled (its handler may have moved the deadline).
        On the ipc bus a datagram (a cycle's frames) is handled whole: frames after a SYNC in it
        are handled before returning (they are latched for the next SYNC either way)."""
        monotonic = time.monotonic
        stop = self._stop
        self._sync_seen = False
        while not stop.is_set():
            if return_on_sync and self._sync_seen:
                return
            now = monotonic()
            if now >= deadline_s:
                return
            if self._failed:
                stop.wait(deadline_s - now)
                return
            due = self._next_due()
            if now >= due:
                self._link.begin_batch()  # the drives' heartbeats, due together: one send
                try:
                    self._nmt.produce_heartbeats(now)
                finally:
                    self._link.flush()
                self._link.release_due(now)
                due = self._next_due()
            try:
                if now >= self._next_check_s:
                    # Judge the master's silence only with nothing of it still queued: a stall of
                    # this thread must not pass for a silent master.
                    self._next_check_s = now + _CHECK_PERIOD_S
                    if self._drain():
                        self._watch.check(monotonic())
                    if return_on_sync and self._sync_seen:
                        # A SYNC among the drained frames: return now, not after the next frame
                        # (a free-running target would otherwise step its physics a period late,
                        # into the next cycle's frames; measured: one exchange in 5 delayed 300 µs).
                        return
                got = self._receive(max(0.0, min(_POLL_S, due - now, deadline_s - now)))
            except Exception:  # the bus went away: nothing left to emulate
                if not stop.is_set():
                    log.exception("emulated drives: receive failed")
                self._failed = True
                return
            if not got:
                self._watch.check(monotonic())  # nothing queued: the silence is real

    def _drain(self) -> bool:
        """Handle every frame already queued; False if they kept coming (no empty queue seen)."""
        for _ in range(_DRAIN_MAX):  # frames, or datagrams on the ipc bus
            if not self._receive(0.0):
                return True
        return False

    def _dispatch(self, cob_id: int, data: bytes | bytearray) -> None:
        """A standard-identifier data frame. The drives' own COB-IDs (RPDOs, SDO requests: six of
        the seven frames of a cycle) are looked up first; SYNC and NMT are not among them."""
        entry = self._by_cob.get(cob_id)
        if entry is not None:
            handler, drive = entry
            if handler(drive, data) is False:
                self._malformed += 1
            return
        if cob_id == fr.SYNC_COB_ID:
            if len(data) > 1 or (len(data) == 1 and not 1 <= data[0] <= 240):
                self._malformed += 1
                return
            self._on_sync(data[0] if data else 0)
            return
        if cob_id == fr.NMT_COB_ID:
            try:
                command, target = fr.decode_nmt(bytes(data))
            except fr.MalformedFrameError:
                self._malformed += 1
                return
            now = time.monotonic()
            for drive in self._drives:
                if target in (0, drive.node_id):
                    self._nmt.on_command(drive, command, now)
            return
        if not self._watch.on_master_heartbeat(cob_id, time.monotonic()):
            self._unknown += 1  # other nodes' frames (TPDOs, heartbeats) land here too

    def _on_sdo(self, drive: EmulatedDrive, data: bytes | bytearray) -> None:
        if drive.nmt is fr.NmtState.STOPPED:
            return
        if len(data) != 8:
            self._malformed += 1
            return
        drive.node.sdo.on_request(fr.SDO_RX_BASE + drive.node_id, bytes(data), time.time())

    def _on_sync(self, counter: int) -> None:
        """Everything a SYNC triggers, on the receiving thread: latch set-points and step the state
        machines, run the plant handler, answer with every drive's TPDO(s) back to back."""
        self._syncs += 1
        self._sync_seen = True
        self._sync_counter = counter
        p402.step_all(self._link, self._drives, monotonic())
        handler = self._sync_handler
        if handler is not None:
            try:
                handler()
            except Exception:  # keep the bus alive; the plant owner logs its own
                log.exception("SYNC handler failed")
        self._answer.send(self._feedback, counter)

    # --- sending ---------------------------------------------------------------------------------

    def _emit_from_cob(self, cob_id: int, data: bytes) -> None:
        node_id = cob_id & 0x7F
        for drive in self._drives:
            if drive.node_id == node_id:
                self._link.emit(drive, cob_id, data)
                return
        self._link.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    def _drive(self, node_id: int) -> EmulatedDrive:
        for drive in self._drives:
            if drive.node_id == node_id:
                return drive
        raise ValueError(f"no emulated drive with node id {node_id} (have {self.config.node_ids})")


def make_drive_bank(bus: can.BusABC, node_ids: tuple[int, ...], config: Any, own_thread: bool = True) -> EmulatedDrives:
    """Started drives for the target server; ``config`` is a ``sim_target.config.TargetConfig``.
    ``own_thread=False``: the server serves them on its own thread (:meth:`EmulatedDrives.serve_until`)."""
    drives_cfg = config.drives
    drives = EmulatedDrives(
        bus,
        EmulatedDrivesConfig(
            node_ids=tuple(node_ids),
            encoder_counts_per_rev=drives_cfg.encoder_counts_per_rev,
            heartbeat_producer_ms=drives_cfg.heartbeat_producer_ms,
            profiles=drives_cfg.profiles,
        ),
    )
    drives.start(own_thread=own_thread)
    return drives
