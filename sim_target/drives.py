"""N emulated CiA 402 joint drives (cyclic synchronous torque) on one python-can bus.

They speak exactly the protocol of :mod:`drivers.cia402` (same codec, same EDS, same state-machine
table) so the runtime's driver cannot tell them from real drives. No pybullet, no hil_runtime: the
plant is reached only through the calls below, made by ``sim_target/server.py``.

API (the server's ``DriveBank``)::

    drives = EmulatedDrives(bus, EmulatedDrivesConfig(node_ids=(1, 2, 3, 4, 5, 6)))
    drives.start()                       # boot-up messages, receive thread (make_drive_bank starts)
    drives.set_sync_handler(fn)          # fn() runs on every SYNC, on the receive thread, after the
                                         # RPDO set-points are latched and the state machine stepped,
                                         # before the TPDOs go out
    drives.commanded_torque_nm()         # (N,) torque each drive applies now, 0 unless enabled
    drives.operation_enabled()           # (N,) bool; a joint whose drive is not enabled is braked
    drives.publish_feedback(state)       # JointState-like (position_rad, velocity_rad_s, torque_nm):
                                         # the values the TPDOs of the current/next SYNC carry
    drives.apply_fault(fault)            # kind "frames" (drop/delay/corrupt) or "drive_fault"
    drives.safe_stop(); drives.close()

Lock-step: the SYNC handler steps the plant one period and publishes its state, so each SYNC
advances physics by exactly one period and the TPDOs answering that SYNC carry the new state.
Free-running: the plant steps on its own clock and the handler publishes the latest state.

Per drive: object dictionary from the EDS behind canopen's ``LocalNode`` SDO server (an
independent canopen master can read and write objects), NMT state machine with boot-up and
heartbeat producer (0x1017), CiA 402 power state machine, 0x6072 torque limit, quick stop per
0x605A, EMCY on fault and on fault reset. PDO mappings may only be one of the two layouts in
:mod:`drivers.cia402.od` (classical or FD); anything else is refused with SDO abort 0x06040041.

Fault injection (``EmulatedDrivesConfig.frame_faults`` at start, :meth:`apply_fault` or the
one-shot helpers at run time) acts on the frames the drives send: dropped, delayed, or corrupted
(sent one byte short: a frame that passed the CAN CRC but does not match the mapping, the only
kind of corruption any master can detect).
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import can
import canopen
import numpy as np
from canopen.sdo.exceptions import SdoAbortedError

from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx
from drivers.cia402 import sdo as sdo_codes
from drivers.cia402.scaling import counts_per_rad_from_resolution
from drivers.cia402.state_machine import (
    STATUS_BITS,
    SW_FOLLOWS_COMMAND,
    SW_INTERNAL_LIMIT,
    SW_REMOTE,
    SW_VOLTAGE_ENABLED,
    State,
    apply_controlword,
)

log = logging.getLogger(__name__)

_POLL_S = 0.01  # longest receive wait: heartbeats and delayed frames are serviced at least this often
_NMT_STATE_CODE = {
    fr.NmtState.BOOT_UP: 0,
    fr.NmtState.PRE_OPERATIONAL: 0x7F,
    fr.NmtState.OPERATIONAL: 0x05,
    fr.NmtState.STOPPED: 0x04,
}
_VOLTAGE_STATES = frozenset({State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED,
                             State.QUICK_STOP_ACTIVE})


class JointStateLike(Protocol):
    position_rad: np.ndarray
    velocity_rad_s: np.ndarray
    torque_nm: np.ndarray


@dataclass(frozen=True)
class FrameFaults:
    """Random faults on the frames a drive sends (probabilities per frame, seeded)."""

    drop_probability: float = 0.0
    delay_s: float = 0.0  # every frame held this long
    corrupt_probability: float = 0.0  # sent one byte short
    seed: int = 0

    @property
    def active(self) -> bool:
        return self.drop_probability > 0 or self.delay_s > 0 or self.corrupt_probability > 0


@dataclass(frozen=True)
class EmulatedDrivesConfig:
    node_ids: tuple[int, ...]  # one per joint, joint order
    encoder_counts_per_rev: int = 1 << 20  # 0x608F:01 (joint side, 1 revolution)
    heartbeat_producer_ms: int = 0  # 0x1017 until the master writes it
    eds_path: Path | None = None
    frame_faults: FrameFaults = FrameFaults()  # applied to every drive from the start

    def __post_init__(self) -> None:
        if not self.node_ids or len(set(self.node_ids)) != len(self.node_ids):
            raise ValueError(f"node_ids must be distinct and non-empty, got {self.node_ids}")
        for node_id in self.node_ids:
            fr.check_node_id(node_id)
        if self.encoder_counts_per_rev <= 0:
            raise ValueError("encoder_counts_per_rev must be positive")


@dataclass(frozen=True)
class DriveCounters:
    frames_received: int
    frames_sent: int
    malformed: int
    unknown_cob_id: int
    syncs: int
    dropped_injected: int
    delayed_injected: int
    corrupted_injected: int


@dataclass
class _Policy:
    faults: FrameFaults
    rng: random.Random
    drop_next: int = 0  # one-shot: drop this many TPDO cycles
    corrupt_next: int = 0
    delay_next: int = 0
    delay_next_s: float = 0.0
    silent_heartbeat: bool = False


@dataclass
class _Drive:
    index: int
    node_id: int
    node: canopen.LocalNode
    counts_per_rad: float
    policy: _Policy
    nmt: fr.NmtState = fr.NmtState.BOOT_UP
    state: State = State.SWITCH_ON_DISABLED
    controlword: int = 0
    previous_controlword: int = 0
    target_permille: int = 0
    applied_permille: int = 0
    limited: bool = False
    # cached from the object dictionary (refreshed on SDO write and on reset)
    rated_torque_mnm: int = 1000
    max_torque_permille: int = 1000
    quick_stop_option: int = 2
    heartbeat_ms: int = 0
    next_heartbeat_s: float = math.inf
    rpdo_valid: bool = True
    tpdo1_valid: bool = True
    tpdo2_valid: bool = True
    fd_layout: bool = False  # one FD TPDO (12 bytes, or 16 with the SYNC counter echo)
    fd_sync_echo: bool = False  # the FD TPDO maps 0x2100: it echoes the answered SYNC's counter
    tpdo_msgs: dict[int, can.Message] = field(default_factory=dict)  # reused: send() copies
    error_code: int = 0
    error_register: int = 0
    pending_fault: int | None = None
    mappings: dict[int, list[int]] = field(default_factory=dict)


class _EmuNetwork(canopen.Network):
    """canopen Network with no notifier: LocalNode SDO answers go out through the drive bank."""

    def __init__(self, bank: EmulatedDrives) -> None:
        super().__init__(None)
        self._bank = bank

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._bank._emit_from_cob(can_id, bytes(data))


class EmulatedDrives:
    """The drive bank. Thread model: one receive thread does everything (SYNC, SDO, NMT,
    heartbeats, delayed frames); getters may be called from any thread."""

    def __init__(self, bus: can.BusABC, config: EmulatedDrivesConfig) -> None:
        self.config = config
        self._bus = bus
        self._send_lock = threading.Lock()
        self._sync_handler: Callable[[], None] | None = None
        self._feedback: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        n = len(config.node_ids)
        self.n_joints = n
        eds = config.eds_path or odx.EDS_PATH
        self._network = _EmuNetwork(self)
        self._drives: list[_Drive] = []
        for index, node_id in enumerate(config.node_ids):
            node = canopen.LocalNode(node_id, odx.load_object_dictionary(node_id, eds))
            # This bank runs NMT and heartbeats itself; canopen's NmtSlave would start a python-can
            # periodic task on 0x1017 writes.
            node._write_callbacks.remove(node.nmt.on_write)
            self._network.add_node(node)
            policy = _Policy(config.frame_faults, random.Random(config.frame_faults.seed * 1000 + node_id))
            drive = _Drive(index, node_id, node, counts_per_rad_from_resolution(config.encoder_counts_per_rev),
                           policy)
            node.add_read_callback(self._make_read_callback(drive))
            node.add_write_callback(self._make_write_callback(drive))
            self._drives.append(drive)
            self._reset_objects(drive, communication_only=False)
        self._by_cob: dict[int, tuple[Callable[[_Drive, bytearray], None], _Drive]] = {}
        for drive in self._drives:
            self._by_cob[fr.RPDO1_BASE + drive.node_id] = (self._on_rpdo, drive)
            self._by_cob[fr.SDO_RX_BASE + drive.node_id] = (self._on_sdo, drive)
        self._delayed: list[tuple[float, int, can.Message]] = []
        self._delay_seq = itertools.count()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._received = 0
        self._sent = 0
        self._malformed = 0
        self._unknown = 0
        self._syncs = 0
        self._dropped = 0
        self._delayed_count = 0
        self._corrupted = 0
        self._sync_counter = 0  # counter byte of the last SYNC (0: the SYNC carried none)

    # --- the server's interface ------------------------------------------------------------------

    def start(self) -> None:
        """Boot every drive (boot-up message, NMT pre-operational) and start receiving."""
        if self._thread is not None:
            return
        for drive in self._drives:
            self._boot(drive)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="emulated-drives", daemon=True)
        self._thread.start()

    def set_sync_handler(self, handler: Callable[[], None] | None) -> None:
        self._sync_handler = handler

    def commanded_torque_nm(self) -> np.ndarray:
        return np.array(
            [d.applied_permille * d.rated_torque_mnm * 1e-6 if d.state is State.OPERATION_ENABLED else 0.0
             for d in self._drives]
        )

    def operation_enabled(self) -> np.ndarray:
        return np.array([d.state is State.OPERATION_ENABLED for d in self._drives], dtype=bool)

    def brake_engaged(self) -> np.ndarray:
        return ~self.operation_enabled()

    def states(self) -> tuple[State, ...]:
        return tuple(d.state for d in self._drives)

    def nmt_states(self) -> tuple[fr.NmtState, ...]:
        return tuple(d.nmt for d in self._drives)

    def publish_feedback(self, state: JointStateLike) -> None:
        """The joint state the TPDOs answering the current (inside the SYNC handler) or next SYNC
        carry. Sync TPDOs only ever go out on SYNC (CiA 301)."""
        self._feedback = (
            np.asarray(state.position_rad, dtype=np.float64),
            np.asarray(state.velocity_rad_s, dtype=np.float64),
            np.asarray(state.torque_nm, dtype=np.float64),
        )

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

    # --- fault injection (run time) --------------------------------------------------------------

    def inject_drive_fault(self, node_id: int, error_code: int = fr.EMCY_OVERCURRENT) -> None:
        """The drive goes to Fault at its next SYNC and sends EMCY ``error_code``."""
        self._drive(node_id).pending_fault = error_code

    def drop_tpdos(self, node_id: int, cycles: int = 1) -> None:
        self._drive(node_id).policy.drop_next += cycles

    def corrupt_tpdos(self, node_id: int, cycles: int = 1) -> None:
        self._drive(node_id).policy.corrupt_next += cycles

    def delay_tpdos(self, node_id: int, delay_s: float, cycles: int = 1) -> None:
        policy = self._drive(node_id).policy
        policy.delay_next += cycles
        policy.delay_next_s = delay_s

    def silence_heartbeat(self, node_id: int, silent: bool = True) -> None:
        self._drive(node_id).policy.silent_heartbeat = silent

    @property
    def counters(self) -> DriveCounters:
        return DriveCounters(self._received, self._sent, self._malformed, self._unknown, self._syncs,
                             self._dropped, self._delayed_count, self._corrupted)

    # --- receive thread --------------------------------------------------------------------------

    def _run(self) -> None:
        bus = self._bus
        by_cob = self._by_cob
        monotonic = time.monotonic
        while not self._stop.is_set():
            now = monotonic()
            due = self._next_due()
            if now >= due:
                self._service_timers(now)
                due = self._next_due()
            try:
                msg = bus.recv(min(_POLL_S, max(0.0, due - now)))
            except Exception:  # noqa: BLE001 - the bus went away: nothing left to emulate
                if not self._stop.is_set():
                    log.exception("emulated drives: receive failed")
                return
            if msg is not None:
                self._received += 1
                try:
                    self._dispatch(msg, by_cob)
                except Exception:  # noqa: BLE001 - an emulator bug must not silence the drives
                    log.exception("emulated drives: handling 0x%03X failed", msg.arbitration_id)

    def _dispatch(self, msg: can.Message, by_cob: dict) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            self._malformed += 1
            return
        cob_id = msg.arbitration_id
        data = msg.data
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
            for drive in self._drives:
                if target in (0, drive.node_id):
                    self._on_nmt(drive, command)
            return
        entry = by_cob.get(cob_id)
        if entry is None:
            self._unknown += 1  # other nodes' frames (TPDOs, heartbeats) land here too
            return
        handler, drive = entry
        handler(drive, data)

    def _on_rpdo(self, drive: _Drive, data: bytearray) -> None:
        if drive.nmt is not fr.NmtState.OPERATIONAL or not drive.rpdo_valid:
            return  # PDOs are ignored outside NMT operational (CiA 301)
        if len(data) != fr.RPDO_LENGTH:
            self._malformed += 1
            return
        drive.controlword, drive.target_permille = fr.decode_rpdo(data)

    def _on_sdo(self, drive: _Drive, data: bytearray) -> None:
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
        self._sync_counter = counter
        drives = self._drives
        for drive in drives:
            self._step_drive(drive)
        handler = self._sync_handler
        if handler is not None:
            try:
                handler()
            except Exception:  # noqa: BLE001 - keep the bus alive; the plant owner logs its own
                log.exception("SYNC handler failed")
        position, velocity, torque = self._scaled_feedback()
        for drive in drives:
            if drive.nmt is fr.NmtState.OPERATIONAL:
                i = drive.index
                self._send_tpdos(drive, position[i], velocity[i], torque[i])

    def _scaled_feedback(self) -> tuple[list[int], list[int], list[int]]:
        """The published state in each drive's units (counts, counts/s, ‰), all joints at once.
        np.rint rounds half to even exactly like round(), so the frames are bit-identical."""
        feedback = self._feedback
        n = self.n_joints
        if feedback is None:
            return [0] * n, [0] * n, [0] * n
        position, velocity, torque = feedback
        counts = np.array([d.counts_per_rad for d in self._drives])
        rated = np.array([d.rated_torque_mnm for d in self._drives], dtype=np.float64)
        return (
            np.clip(np.rint(position * counts), -(2**31), 2**31 - 1).astype(np.int64).tolist(),
            np.clip(np.rint(velocity * counts), -(2**31), 2**31 - 1).astype(np.int64).tolist(),
            np.clip(np.rint(torque * 1e6 / rated), -32768, 32767).astype(np.int64).tolist(),
        )

    def _step_drive(self, drive: _Drive) -> None:
        if drive.pending_fault is not None:
            code, drive.pending_fault = drive.pending_fault, None
            self._enter_fault(drive, code)
        if drive.nmt is not fr.NmtState.OPERATIONAL:
            drive.applied_permille = 0
            return
        previous_state = drive.state
        drive.state = apply_controlword(drive.state, drive.controlword, drive.previous_controlword,
                                        drive.quick_stop_option)
        drive.previous_controlword = drive.controlword
        if previous_state is State.FAULT and drive.state is not State.FAULT:
            drive.error_code = 0
            drive.error_register = 0
            self._emit(drive, fr.EMCY_BASE + drive.node_id, fr.encode_emcy(fr.EMCY_ERROR_RESET, 0))
        if drive.state is State.OPERATION_ENABLED:
            limit = drive.max_torque_permille
            target = drive.target_permille
            drive.limited = not -limit <= target <= limit
            drive.applied_permille = max(-limit, min(limit, target))
        else:
            drive.limited = False
            drive.applied_permille = 0

    def _enter_fault(self, drive: _Drive, code: int) -> None:
        drive.state = State.FAULT
        drive.applied_permille = 0
        drive.error_code = code
        drive.error_register = fr.ERROR_REGISTER_GENERIC | (
            fr.ERROR_REGISTER_CURRENT if 0x2000 <= code < 0x3000 else 0
        )
        self._emit(drive, fr.EMCY_BASE + drive.node_id, fr.encode_emcy(code, drive.error_register))

    def _statusword(self, drive: _Drive) -> int:
        word = STATUS_BITS.get(drive.state, 0) | SW_REMOTE
        if drive.state in _VOLTAGE_STATES:
            word |= SW_VOLTAGE_ENABLED
        if drive.state is State.OPERATION_ENABLED:
            word |= SW_FOLLOWS_COMMAND
            if drive.limited:
                word |= SW_INTERNAL_LIMIT
        return word

    def _send_tpdos(self, drive: _Drive, position_counts: int, velocity_counts: int, torque_permille: int) -> None:
        statusword = self._statusword(drive)
        policy = drive.policy
        if drive.fd_sync_echo and drive.tpdo1_valid and not (
            policy.faults.active or policy.drop_next or policy.corrupt_next or policy.delay_next
        ):
            # The hot path: pack into the drive's own message and send it, nothing allocated here.
            msg = drive.tpdo_msgs[fr.TPDO1_BASE]
            fr.encode_tpdo_fd_sync_into(msg.data, statusword, torque_permille, position_counts,
                                      velocity_counts, self._sync_counter)
            self._send(msg)
            return
        if policy.drop_next > 0:
            policy.drop_next -= 1
            self._dropped += 1
            return
        corrupt = policy.corrupt_next > 0
        if corrupt:
            policy.corrupt_next -= 1
        delay_s = 0.0
        if policy.delay_next > 0:
            policy.delay_next -= 1
            delay_s = policy.delay_next_s
        if drive.fd_layout:
            if drive.tpdo1_valid:
                if drive.fd_sync_echo:
                    data = fr.encode_tpdo_fd_sync(statusword, torque_permille, position_counts, velocity_counts,
                                                self._sync_counter)
                else:
                    data = fr.encode_tpdo_fd(statusword, torque_permille, position_counts, velocity_counts)
                self._emit(drive, fr.TPDO1_BASE + drive.node_id, data, fd=True, corrupt=corrupt, delay_s=delay_s)
            return
        if drive.tpdo1_valid:
            data = fr.encode_tpdo1(statusword, torque_permille, position_counts)
            self._emit(drive, fr.TPDO1_BASE + drive.node_id, data, corrupt=corrupt, delay_s=delay_s)
        if drive.tpdo2_valid:
            data = fr.encode_tpdo2(velocity_counts)
            self._emit(drive, fr.TPDO2_BASE + drive.node_id, data, corrupt=corrupt, delay_s=delay_s)

    # --- NMT and heartbeat -----------------------------------------------------------------------

    def _boot(self, drive: _Drive) -> None:
        drive.nmt = fr.NmtState.BOOT_UP
        self._emit(drive, fr.HEARTBEAT_BASE + drive.node_id, fr.encode_heartbeat(fr.NmtState.BOOT_UP))
        drive.nmt = fr.NmtState.PRE_OPERATIONAL
        self._schedule_heartbeat(drive, time.monotonic())

    def _on_nmt(self, drive: _Drive, command: fr.NmtCommand) -> None:
        was_operational = drive.nmt is fr.NmtState.OPERATIONAL
        if command is fr.NmtCommand.START:
            drive.nmt = fr.NmtState.OPERATIONAL
        elif command is fr.NmtCommand.STOP:
            drive.nmt = fr.NmtState.STOPPED
        elif command is fr.NmtCommand.ENTER_PRE_OPERATIONAL:
            drive.nmt = fr.NmtState.PRE_OPERATIONAL
        elif command is fr.NmtCommand.RESET_NODE:
            self._reset_objects(drive, communication_only=False)
            drive.state = State.SWITCH_ON_DISABLED
            drive.error_code = drive.error_register = 0
            self._boot(drive)
        elif command is fr.NmtCommand.RESET_COMMUNICATION:
            self._reset_objects(drive, communication_only=True)
            self._boot(drive)
        if was_operational and drive.nmt is not fr.NmtState.OPERATIONAL:
            # Losing the master's PDOs while enabled: torque off, brake on (the 0x6007 default).
            if drive.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
                drive.state = State.SWITCH_ON_DISABLED
            drive.applied_permille = 0
            drive.controlword = drive.previous_controlword = 0
            drive.target_permille = 0

    def _schedule_heartbeat(self, drive: _Drive, now: float) -> None:
        drive.next_heartbeat_s = now + drive.heartbeat_ms / 1000 if drive.heartbeat_ms > 0 else math.inf

    def _next_due(self) -> float:
        due = min(d.next_heartbeat_s for d in self._drives)
        if self._delayed:
            due = min(due, self._delayed[0][0])
        return due

    def _service_timers(self, now: float) -> None:
        for drive in self._drives:
            if now >= drive.next_heartbeat_s:
                if not drive.policy.silent_heartbeat:
                    self._emit(drive, fr.HEARTBEAT_BASE + drive.node_id,
                               bytes((_NMT_STATE_CODE[drive.nmt],)))
                # Keep the schedule absolute (no drift), but never burst after a stall.
                drive.next_heartbeat_s = max(drive.next_heartbeat_s + drive.heartbeat_ms / 1000, now)
        while self._delayed and self._delayed[0][0] <= now:
            _, _, msg = heapq.heappop(self._delayed)
            self._send(msg)

    # --- object dictionary -----------------------------------------------------------------------

    def _reset_objects(self, drive: _Drive, communication_only: bool) -> None:
        store = drive.node.data_store
        for index in list(store):
            if not communication_only or 0x1000 <= index <= 0x1FFF:
                del store[index]
        drive.node.data_store.setdefault(odx.ENCODER_RESOLUTION, {})[1] = (
            self.config.encoder_counts_per_rev.to_bytes(4, "little")
        )
        if self.config.heartbeat_producer_ms:
            store.setdefault(odx.HEARTBEAT_PRODUCER, {})[0] = self.config.heartbeat_producer_ms.to_bytes(2, "little")
        od = drive.node.object_dictionary

        def value(index: int, subindex: int = 0) -> int:
            var = od[index] if subindex == 0 and isinstance(od[index], canopen.objectdictionary.ODVariable) \
                else od[index][subindex]
            raw = store.get(index, {}).get(subindex)
            return int(var.decode_raw(raw)) if raw is not None else int(var.default)

        drive.rated_torque_mnm = value(odx.RATED_TORQUE)
        drive.max_torque_permille = value(odx.MAX_TORQUE)
        drive.quick_stop_option = value(odx.QUICK_STOP_OPTION)
        drive.heartbeat_ms = value(odx.HEARTBEAT_PRODUCER)
        drive.rpdo_valid = not value(odx.RPDO1_COMM, 1) & odx.PDO_COB_ID_INVALID
        drive.tpdo1_valid = not value(odx.TPDO1_COMM, 1) & odx.PDO_COB_ID_INVALID
        drive.tpdo2_valid = not value(odx.TPDO2_COMM, 1) & odx.PDO_COB_ID_INVALID
        drive.mappings = {
            mapping: [value(mapping, k) for k in range(value(mapping, 0) + 1)][1:]
            for mapping in (odx.RPDO1_MAP, odx.TPDO1_MAP, odx.TPDO2_MAP)
        }
        self._set_tpdo1_layout(drive, len(drive.mappings[odx.TPDO1_MAP]))
        self._schedule_heartbeat(drive, time.monotonic())

    @staticmethod
    def _set_tpdo1_layout(drive: _Drive, n_entries: int) -> None:
        drive.fd_layout = n_entries in (len(odx.FD_LAYOUT.tpdo1), len(odx.FD_SYNC_LAYOUT.tpdo1))
        drive.fd_sync_echo = n_entries == len(odx.FD_SYNC_LAYOUT.tpdo1)
        cob_id = fr.TPDO1_BASE + drive.node_id
        drive.tpdo_msgs[fr.TPDO1_BASE] = can.Message(
            arbitration_id=cob_id, data=bytearray(fr.TPDO_FD_SYNC_LENGTH), is_extended_id=False, is_fd=True,
            bitrate_switch=True,
        )

    def _make_read_callback(self, drive: _Drive) -> Callable[..., int | None]:
        def read(index: int, subindex: int, od: Any) -> int | None:
            feedback = self._feedback
            i = drive.index
            if index == odx.STATUSWORD:
                return self._statusword(drive)
            if index == odx.CONTROLWORD:
                return drive.controlword
            if index == odx.TARGET_TORQUE:
                return drive.target_permille
            if index == odx.ERROR_CODE:
                return drive.error_code
            if index == odx.ERROR_REGISTER:
                return drive.error_register
            if index == odx.SYNC_COUNTER_ECHO:
                return self._sync_counter
            if index == odx.MODES_DISPLAY:
                mode = drive.node.data_store.get(odx.MODES_OF_OPERATION, {}).get(0)
                return mode[0] if mode is not None else odx.MODE_CYCLIC_SYNC_TORQUE
            if index in (odx.POSITION_ACTUAL, odx.VELOCITY_ACTUAL, odx.TORQUE_ACTUAL):
                if feedback is None:
                    return 0
                if index == odx.POSITION_ACTUAL:
                    return _clamp32(round(float(feedback[0][i]) * drive.counts_per_rad))
                if index == odx.VELOCITY_ACTUAL:
                    return _clamp32(round(float(feedback[1][i]) * drive.counts_per_rad))
                return _clamp16(round(float(feedback[2][i]) * 1e6 / drive.rated_torque_mnm))
            return None

        return read

    def _make_write_callback(self, drive: _Drive) -> Callable[..., None]:
        pdo_comm = {odx.RPDO1_COMM: fr.RPDO1_BASE, odx.TPDO1_COMM: fr.TPDO1_BASE, odx.TPDO2_COMM: fr.TPDO2_BASE}
        layouts = {
            odx.RPDO1_MAP: (odx.CLASSICAL_LAYOUT.rpdo1, odx.FD_LAYOUT.rpdo1),
            odx.TPDO1_MAP: (odx.CLASSICAL_LAYOUT.tpdo1, odx.FD_LAYOUT.tpdo1, odx.FD_SYNC_LAYOUT.tpdo1),
            odx.TPDO2_MAP: (odx.CLASSICAL_LAYOUT.tpdo2, odx.FD_LAYOUT.tpdo2),
        }
        comm_of_map = {odx.RPDO1_MAP: odx.RPDO1_COMM, odx.TPDO1_MAP: odx.TPDO1_COMM, odx.TPDO2_MAP: odx.TPDO2_COMM}

        def write(index: int, subindex: int, od: Any, data: bytes) -> None:
            value = od.decode_raw(data)
            if index == odx.MODES_OF_OPERATION and value != odx.MODE_CYCLIC_SYNC_TORQUE:
                raise SdoAbortedError(sdo_codes.ABORT_INVALID_VALUE)  # only mode 10 is emulated
            if index == odx.RATED_TORQUE:
                if value <= 0:
                    raise SdoAbortedError(sdo_codes.ABORT_VALUE_TOO_LOW)
                drive.rated_torque_mnm = value
            elif index == odx.MAX_TORQUE:
                drive.max_torque_permille = value
            elif index == odx.QUICK_STOP_OPTION:
                if not 0 <= value <= 8:
                    raise SdoAbortedError(sdo_codes.ABORT_INVALID_VALUE)
                drive.quick_stop_option = value
            elif index == odx.HEARTBEAT_PRODUCER:
                drive.heartbeat_ms = value
                self._schedule_heartbeat(drive, time.monotonic())
            elif index == odx.CONTROLWORD:
                drive.controlword = value
            elif index == odx.TARGET_TORQUE:
                drive.target_permille = value
            elif index in pdo_comm and subindex == 1:
                if value & 0x7FF != pdo_comm[index] + drive.node_id:
                    raise SdoAbortedError(sdo_codes.ABORT_INVALID_VALUE)  # predefined set only
                valid = not value & odx.PDO_COB_ID_INVALID
                if valid and index in (odx.TPDO1_COMM, odx.TPDO2_COMM, odx.RPDO1_COMM):
                    self._check_mapping_complete(drive, index)
                setattr(drive, {odx.RPDO1_COMM: "rpdo_valid", odx.TPDO1_COMM: "tpdo1_valid",
                                odx.TPDO2_COMM: "tpdo2_valid"}[index], valid)
            elif index in pdo_comm and subindex == 2:
                if value != odx.TRANSMISSION_SYNC_EVERY:
                    raise SdoAbortedError(sdo_codes.ABORT_INVALID_VALUE)  # synchronous, every SYNC
            elif index in layouts:
                if getattr(drive, {odx.RPDO1_COMM: "rpdo_valid", odx.TPDO1_COMM: "tpdo1_valid",
                                   odx.TPDO2_COMM: "tpdo2_valid"}[comm_of_map[index]]):
                    raise SdoAbortedError(sdo_codes.ABORT_DEVICE_STATE)  # map only a disabled PDO
                entries = drive.mappings[index]
                if subindex == 0:
                    if value == 0:
                        drive.mappings[index] = []
                        return
                    if not any(len(layout) == value for layout in layouts[index]):
                        raise SdoAbortedError(sdo_codes.ABORT_PDO_LENGTH)
                    staged = drive.node.data_store.get(index, {})
                    chosen = [int.from_bytes(staged[k], "little") if k in staged else None
                              for k in range(1, value + 1)]
                    if not any(list(layout) == chosen for layout in layouts[index]):
                        raise SdoAbortedError(sdo_codes.ABORT_NOT_MAPPABLE)
                    drive.mappings[index] = chosen  # type: ignore[assignment]
                    if index == odx.TPDO1_MAP:
                        self._set_tpdo1_layout(drive, value)
                    return
                if entries:
                    raise SdoAbortedError(sdo_codes.ABORT_DEVICE_STATE)  # clear sub 0 first
                allowed = {layout[subindex - 1] for layout in layouts[index] if len(layout) >= subindex}
                if value not in allowed and value != 0:
                    raise SdoAbortedError(sdo_codes.ABORT_NOT_MAPPABLE)

        return write

    def _check_mapping_complete(self, drive: _Drive, comm: int) -> None:
        mapping = {odx.RPDO1_COMM: odx.RPDO1_MAP, odx.TPDO1_COMM: odx.TPDO1_MAP, odx.TPDO2_COMM: odx.TPDO2_MAP}[comm]
        if not drive.mappings[mapping]:
            raise SdoAbortedError(sdo_codes.ABORT_DEVICE_STATE)  # nothing mapped: cannot enable

    # --- sending ---------------------------------------------------------------------------------

    def _emit_from_cob(self, cob_id: int, data: bytes) -> None:
        node_id = cob_id & 0x7F
        for drive in self._drives:
            if drive.node_id == node_id:
                self._emit(drive, cob_id, data)
                return
        self._send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    def _emit(self, drive: _Drive, cob_id: int, data: bytes, fd: bool = False, corrupt: bool = False,
              delay_s: float = 0.0) -> None:
        faults = drive.policy.faults
        if faults.active:
            rng = drive.policy.rng
            if faults.drop_probability and rng.random() < faults.drop_probability:
                self._dropped += 1
                return
            if faults.corrupt_probability and rng.random() < faults.corrupt_probability:
                corrupt = True
            delay_s = max(delay_s, faults.delay_s)
        if corrupt and data:
            data = data[:-1]
            self._corrupted += 1
        msg = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False, is_fd=fd, bitrate_switch=fd)
        if delay_s > 0:
            self._delayed_count += 1
            heapq.heappush(self._delayed, (time.monotonic() + delay_s, next(self._delay_seq), msg))
            return
        self._send(msg)

    def _send(self, msg: can.Message) -> None:
        try:
            with self._send_lock:
                self._bus.send(msg)
        except (can.CanError, OSError) as exc:
            log.warning("emulated drives: send 0x%03X failed: %s", msg.arbitration_id, exc)
            return
        self._sent += 1

    def _drive(self, node_id: int) -> _Drive:
        for drive in self._drives:
            if drive.node_id == node_id:
                return drive
        raise ValueError(f"no emulated drive with node id {node_id} (have {self.config.node_ids})")


def _clamp32(value: int) -> int:
    return max(-(2**31), min(2**31 - 1, value))


def _clamp16(value: int) -> int:
    return max(-32768, min(32767, value))


def make_drive_bank(bus: can.BusABC, node_ids: tuple[int, ...], config: Any) -> EmulatedDrives:
    """Started drives for the target server; ``config`` is a ``sim_target.config.TargetConfig``."""
    drives_cfg = config.drives
    drives = EmulatedDrives(
        bus,
        EmulatedDrivesConfig(
            node_ids=tuple(node_ids),
            encoder_counts_per_rev=drives_cfg.encoder_counts_per_rev,
            heartbeat_producer_ms=drives_cfg.heartbeat_producer_ms,
        ),
    )
    drives.start()
    return drives
