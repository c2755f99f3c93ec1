"""The drive bus: what the runtime calls to run N CiA 402 joint drives in cyclic synchronous torque.

Transport-independent (any python-can bus from :mod:`drivers.transport`)::

    bus = DriveBus(config)          # frozen DriveBusConfig; refuses an over-budget bus load
    bus.connect()                   # NMT reset -> boot-up, SDO configuration, NMT start
    bus.enable()                    # CiA 402 state machine to Operation Enabled
    while running:
        feedback = bus.exchange(torque_nm)   # RPDOs + SYNC out, TPDOs in: one control cycle
    bus.quick_stop() / bus.disable()
    bus.close()

One :meth:`DriveBus.exchange` per control period sends every drive's RPDO (controlword, target
torque) and one SYNC carrying the CiA 301 SYNC counter (1..240), then waits at most
``feedback_timeout_s`` for every drive's TPDO(s) (statusword, torque, position, velocity). The SYNC
is what makes a lock-stepped target advance.

Reception runs on the caller's thread inside the cycle: frames already queued before the SYNC are
drained first (a TPDO among them belongs to an older cycle: counted late, never used), then the
caller blocks in ``bus.recv`` until every TPDO of this cycle is in or the deadline passes. With
CAN FD each TPDO echoes the SYNC counter (object 0x2100), so a TPDO answering an older SYNC is
recognised even when it arrives after this cycle's SYNC; with classical CAN (no room in the
8-byte TPDO1) only the drain applies. Heartbeat deadlines are checked at the end of every cycle.
A background thread receives only while no cycle runs: blocking during start-up and SDO
transfers (canopen's SDO client waits on it), otherwise it drains the bus when the caller has not
exchanged for ``_IDLE_TAKEOVER_S`` (late frames, heartbeats, EMCY between runs).

Every frame is decoded with the pure codec in :mod:`drivers.cia402`: canopen's PDO map objects
cost ~6.5 µs per TPDO decode and ~3 µs per RPDO encode against ~0.08 µs for the precompiled
structs (benchmarks/bench_can_exchange.py, "codec"), and it is the code the emulated drives share.
Heartbeats (timeout -> HeartbeatLostError), EMCY (-> DriveFaultError with the EMCY code) and SDO
responses (routed to canopen's SDO client, used only at start-up) are handled by whichever thread
receives them; errors are stored and raised by the caller's next ``exchange``/``enable``.
Malformed frames, unknown COB-IDs, late and missing TPDOs never raise on their own: they are
counted (:attr:`DriveBus.counters`); a drive missing its TPDOs for more than
``max_missed_cycles`` consecutive cycles raises :class:`FeedbackTimeoutError`.

Any run-time error raised by :meth:`exchange` (feedback timeout, drive fault, heartbeat loss, a
drive leaving Operation Enabled, transport failure) first quick-stops every drive that still
answers (at most ``_SAFE_STOP_CYCLES`` cycles) and leaves :attr:`enabled` false.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import threading
import time
from collections.abc import Iterator

import can
import canopen
import numpy as np
from canopen.objectdictionary import ODVariable
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx
from drivers.cia402.scaling import counts_per_rad_from_resolution
from drivers.cia402.state_machine import State, decode_statusword_fast, next_controlword
from drivers.config import DriveBusConfig
from drivers.errors import (
    DriveCommandError,
    DriveConfigError,
    DriveError,
    DriveFaultError,
    DriveStateError,
    FeedbackTimeoutError,
    HeartbeatLostError,
    SdoAbortError,
    SdoTimeoutError,
    TransportError,
)
from drivers.feedback import BusCounters, DriveFeedback
from drivers.transport import open_bus

__all__ = ["BusCounters", "DriveBus", "DriveFeedback"]

log = logging.getLogger(__name__)

_RX_POLL_S = 0.005  # background receive (start-up, SDO): longest blocking wait
_IDLE_POLL_S = 0.01  # cyclic mode: the background thread looks this often whether the caller is idle
_IDLE_TAKEOVER_S = 0.02  # no cycle for this long: the background thread drains the bus
_SAFE_STOP_CYCLES = 3  # quick-stop cycles sent after a run-time error (drives that answer confirm)
_QUICK_STOP_STATES = frozenset({State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED})
_CW_ENABLE = 0x000F
_CW_QUICK_STOP = 0x0002
_CW_DISABLE_VOLTAGE = 0x0000
_CW_SHUTDOWN = 0x0006
_CW_FAULT_RESET = 0x0080
_FAULT_STATES = frozenset({State.FAULT, State.FAULT_REACTION_ACTIVE})


class _SdoNetwork(canopen.Network):
    """A canopen Network without its own notifier: sends through the DriveBus, which routes
    SDO responses back from its receive thread."""

    def __init__(self, owner: DriveBus) -> None:
        super().__init__(None)
        self._owner = owner

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._owner._send(can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=False))


class DriveBus:
    """N CiA 402 drives in cyclic synchronous torque on one CAN bus. Not thread-safe: one caller."""

    def __init__(self, config: DriveBusConfig, bus: can.BusABC | None = None) -> None:
        """``bus``: an already open python-can bus to use (not closed by :meth:`close`)."""
        self.config = config
        self.bus_load = config.bus_load()  # raises BusLoadError before touching the bus
        self._bus = bus
        self._owns_bus = bus is None
        self._fd = config.transport.fd
        self.node_ids = config.node_ids
        n = len(self.node_ids)
        self.n_joints = n
        self._layout = odx.FD_SYNC_LAYOUT if self._fd else odx.CLASSICAL_LAYOUT
        self._tpdos_per_drive = 1 if self._fd else 2

        self._max_torque_nm = np.array([j.max_torque_nm for j in config.joints])
        self._permille_per_nm = np.array([1e6 / j.effective_rated_torque_mnm for j in config.joints])
        self._counts_per_rad = np.ones(n)  # read from 0x608F at connect

        # Receive-side state: touched only by the thread that holds _rx_lock (the one calling
        # bus.recv): the caller inside a cycle, or the background thread.
        self._rx_lock = threading.Lock()
        self._caller_rx = False  # True once connected: cycles receive on the caller's thread
        self._wake = threading.Event()
        self._last_cycle_end_s = 0.0
        self._sync_counter = 0
        self._cycle_no = 0
        self._open = False
        self._pending = 0
        self._statusword = [0] * n
        self._torque_pm = [0] * n
        self._position = [0] * n
        self._velocity = [0] * n
        self._got1 = [-1] * n  # cycle in which TPDO1 (or the FD TPDO) last arrived
        self._got2 = [-1] * n
        self._rx_time = [0.0] * n
        self._missed = [0] * n
        self._states: list[State] = [State.UNKNOWN] * n

        self._nmt_state: list[fr.NmtState | None] = [None] * n
        self._booted = [False] * n
        self._last_heartbeat = [0.0] * n
        self._heartbeat_lost = [False] * n
        self._heartbeat_armed = False
        self._last_emcy = [0] * n

        self._errors: collections.deque[DriveError] = collections.deque()
        self._stop = threading.Event()
        self._rx_thread: threading.Thread | None = None
        self._handlers: dict[int, object] = {}

        self._sent = 0
        self._received = 0
        self._dropped = 0
        self._late = 0
        self._malformed = 0
        self._unknown = 0
        self._emcy = 0
        self._heartbeats = 0

        self._network: _SdoNetwork | None = None
        self._nodes: list[canopen.RemoteNode] = []
        self._connected = False
        self._enabled = False

        # Built once; each cycle packs into their data in place (every backend copies or
        # serialises a frame inside send()).
        self._rpdo_msgs = [
            can.Message(
                arbitration_id=fr.RPDO1_BASE + node,
                data=bytearray(fr.RPDO_LENGTH),
                is_extended_id=False,
                is_fd=self._fd,
                bitrate_switch=self._fd,
            )
            for node in self.node_ids
        ]
        self._sync_msg = can.Message(arbitration_id=fr.SYNC_COB_ID, data=bytearray(1), is_extended_id=False)
        self._cycle_msgs = [*self._rpdo_msgs, self._sync_msg]
        self._cw_enable = [_CW_ENABLE] * n
        self._zeros_nm = np.zeros(n)

    # --- public API ------------------------------------------------------------------------------

    @property
    def counters(self) -> BusCounters:
        return BusCounters(
            cycles=self._cycle_no,
            frames_sent=self._sent,
            frames_received=self._received,
            dropped=self._dropped,
            late=self._late,
            malformed=self._malformed,
            unknown_cob_id=self._unknown,
            emcy=self._emcy,
            heartbeats=self._heartbeats,
        )

    @property
    def enabled(self) -> bool:
        return self._enabled

    @property
    def states(self) -> tuple[State, ...]:
        """CiA 402 state of each drive from its last TPDO."""
        return tuple(self._states)

    @property
    def counts_per_rad(self) -> np.ndarray:
        return self._counts_per_rad.copy()

    def connect(self) -> None:
        """Open the bus, reset and configure every drive by SDO, start them (NMT operational)."""
        if self._connected:
            return
        if self._bus is None:
            self._bus = open_bus(self.config.transport)
        self._network = _SdoNetwork(self)
        eds = self.config.eds_path or odx.EDS_PATH
        self._nodes = []
        for node_id in self.node_ids:
            node = canopen.RemoteNode(node_id, odx.load_object_dictionary(node_id, eds))
            node.sdo.RESPONSE_TIMEOUT = self.config.sdo_timeout_s
            self._network.add_node(node)
            self._nodes.append(node)
        self._build_handlers()
        self._stop.clear()
        self._rx_thread = threading.Thread(target=self._rx_loop, name="drive-bus-rx", daemon=True)
        self._rx_thread.start()
        try:
            self._boot_and_configure()
        except BaseException:
            self.close()
            raise
        self._connected = True
        self._last_cycle_end_s = time.monotonic()
        self._caller_rx = True

    def enable(self, hold_torque_nm: np.ndarray | None = None) -> DriveFeedback:
        """Walk every drive to Operation Enabled; returns the last cycle's feedback. Faulted drives
        raise: call :meth:`fault_reset` first.

        ``hold_torque_nm`` (N,) is sent with every controlword of the walk (clipped and quantised
        like :meth:`exchange`). A drive applies it from the SYNC at which it enters Operation
        Enabled, so the arm does not fall for the cycles between brake release and the first
        :meth:`exchange`: pass the gravity torque at the current position. None: zero torque (the
        joints sag for those cycles, one or two periods).
        """
        self._require_connected()
        self._raise_pending()
        if hold_torque_nm is None:
            permille, commanded = [0] * self.n_joints, self._zeros_nm
        else:
            permille, commanded = self._setpoints(hold_torque_nm, "hold_torque_nm")
        deadline = time.monotonic() + self.config.state_change_timeout_s
        while True:
            controlwords = []
            for i, state in enumerate(self._states):
                if state in _FAULT_STATES:
                    raise DriveFaultError(
                        self.node_ids[i], self._last_emcy[i], "in Fault: call fault_reset() first"
                    )
                controlwords.append(self._step_towards(state, State.OPERATION_ENABLED))
            feedback = self._cycle(controlwords, permille, commanded)
            self._raise_pending()
            if feedback.fresh.all() and all(s is State.OPERATION_ENABLED for s in feedback.states):
                self._missed = [0] * self.n_joints
                self._enabled = True
                return feedback
            if time.monotonic() > deadline:
                raise DriveStateError(f"not in operation enabled after "
                                      f"{self.config.state_change_timeout_s} s: {self._describe_states()}")

    def exchange(self, torque_nm: np.ndarray) -> DriveFeedback:
        """One control cycle: send the torque set-points, return this cycle's feedback.

        Set-points are clipped to each joint's max torque and quantised to 1 ‰ of its rated
        torque; ``commanded_torque_nm`` in the result is what was actually sent.
        """
        if not self._enabled:
            self._raise_pending()
            raise DriveStateError("drives are not enabled: call enable() first")
        try:
            self._raise_pending()
            permille, commanded = self._setpoints(torque_nm, "torque_nm")  # DriveCommandError: nothing sent
            feedback = self._cycle(self._cw_enable, permille, commanded)
            self._raise_pending()
            self._check_cycle(feedback)
        except (FeedbackTimeoutError, DriveFaultError, HeartbeatLostError, DriveStateError, TransportError):
            self._fail_safe()
            raise
        return feedback

    def _setpoints(self, torque_nm: np.ndarray, name: str) -> tuple[list[int], np.ndarray]:
        """(‰ of rated torque per drive, the torque in N·m those stand for); refuses bad input."""
        torque = np.asarray(torque_nm, dtype=np.float64)
        if torque.shape != (self.n_joints,):
            raise DriveCommandError(f"{name} has shape {torque.shape}, expected ({self.n_joints},)")
        if not np.isfinite(torque).all():
            bad = [self.node_ids[i] for i in np.flatnonzero(~np.isfinite(torque))]
            raise DriveCommandError(f"non-finite torque set-point for drive(s) {bad}")
        permille = np.rint(np.clip(torque, -self._max_torque_nm, self._max_torque_nm) * self._permille_per_nm)
        return permille.astype(np.int64).tolist(), permille / self._permille_per_nm

    def _fail_safe(self) -> None:
        """After a run-time error: not enabled, and every drive that still answers quick-stopped
        (a few cycles at most, never raising: the original error is what the caller gets)."""
        self._enabled = False
        if self._bus is None or not self._connected:
            return
        codes = [_CW_QUICK_STOP] * self.n_joints
        zeros = [0] * self.n_joints
        for _ in range(_SAFE_STOP_CYCLES):
            try:
                feedback = self._cycle(codes, zeros, self._zeros_nm)
            except DriveError as exc:
                log.warning("quick stop after an error failed: %s", exc)
                return
            if all(not fresh or s in _QUICK_STOP_STATES or s in _FAULT_STATES
                   for fresh, s in zip(feedback.fresh, feedback.states)):
                return

    def quick_stop(self) -> tuple[State, ...]:
        """Quick stop every drive (zero torque, brake); best effort, never raises for drive faults.

        Returns the states reached (Quick Stop Active or Switch On Disabled, per 0x605A).
        """
        return self._stop_drives(_CW_QUICK_STOP, {State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED})

    def disable(self) -> tuple[State, ...]:
        """Disable voltage on every drive (Switch On Disabled: brake holds). Best effort."""
        return self._stop_drives(_CW_DISABLE_VOLTAGE, {State.SWITCH_ON_DISABLED})

    def fault_reset(self) -> None:
        """Reset faulted drives to Switch On Disabled (rising edge of controlword bit 7)."""
        self._require_connected()
        self._errors.clear()
        deadline = time.monotonic() + self.config.state_change_timeout_s
        zeros = [0] * self.n_joints
        self._cycle([_CW_DISABLE_VOLTAGE] * self.n_joints, zeros, self._zeros_nm)
        while True:
            feedback = self._cycle([_CW_FAULT_RESET] * self.n_joints, zeros, self._zeros_nm)
            if feedback.fresh.all() and not any(s in _FAULT_STATES for s in feedback.states):
                self._errors.clear()  # EMCY "error reset" frames may have been queued as errors
                return
            if time.monotonic() > deadline:
                raise DriveStateError(f"fault reset failed: {self._describe_states()}")
            self._cycle([_CW_DISABLE_VOLTAGE] * self.n_joints, zeros, self._zeros_nm)

    def sdo_read(self, node_id: int, index: int, subindex: int = 0) -> bytes:
        """Read an object by SDO (start-up and diagnostics; not for the control loop)."""
        node = self._node(node_id)
        try:
            with self._background_receive():
                return node.sdo.upload(index, subindex)
        except SdoAbortedError as exc:
            raise SdoAbortError(node_id, index, subindex, exc.code) from None
        except SdoCommunicationError as exc:
            raise SdoTimeoutError(f"drive {node_id} SDO 0x{index:04X}:{subindex:02X}: {exc}") from None

    def sdo_write(self, node_id: int, index: int, subindex: int, value: int | bytes) -> None:
        """Write an object by SDO; an int is encoded with the EDS data type of the object."""
        node = self._node(node_id)
        if isinstance(value, int):
            var = _od_variable(node, index, subindex)
            if var is None:
                raise SdoAbortError(node_id, index, subindex, 0x06020000)
            value = var.encode_raw(value)
        try:
            with self._background_receive():
                node.sdo.download(index, subindex, value)
        except SdoAbortedError as exc:
            raise SdoAbortError(node_id, index, subindex, exc.code) from None
        except SdoCommunicationError as exc:
            raise SdoTimeoutError(f"drive {node_id} SDO 0x{index:04X}:{subindex:02X}: {exc}") from None

    def sdo_read_int(self, node_id: int, index: int, subindex: int = 0) -> int:
        data = self.sdo_read(node_id, index, subindex)
        var = _od_variable(self._node(node_id), index, subindex)
        if var is None:
            return int.from_bytes(data, "little")
        return int(var.decode_raw(data))

    def nmt(self, command: fr.NmtCommand, node_id: int = 0) -> None:
        self._send(can.Message(arbitration_id=fr.NMT_COB_ID, data=fr.encode_nmt(command, node_id),
                               is_extended_id=False))

    def close(self) -> None:
        """Disable the drives if enabled, stop their PDOs (NMT pre-operational), release the bus."""
        if self._enabled:
            try:
                self.disable()
            except DriveError as exc:
                log.warning("disable on close failed: %s", exc)
        self._enabled = False
        if self._bus is not None and self._rx_thread is not None and self._rx_thread.is_alive():
            self._heartbeat_armed = False
            for node_id in self.node_ids:
                try:
                    self.nmt(fr.NmtCommand.ENTER_PRE_OPERATIONAL, node_id)
                except DriveError:
                    break
        self._stop.set()
        self._wake.set()
        if self._rx_thread is not None:
            self._rx_thread.join(timeout=1.0)
            self._rx_thread = None
        if self._owns_bus and self._bus is not None:
            self._bus.shutdown()
            self._bus = None
        self._connected = False

    def __enter__(self) -> DriveBus:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the cycle -------------------------------------------------------------------------------

    def _cycle(self, controlwords: list[int], permille: list[int], commanded_nm: np.ndarray) -> DriveFeedback:
        bus = self._bus
        if bus is None:
            raise TransportError("bus is closed")
        n = self.n_joints
        pack = fr.pack_rpdo_into
        with self._rx_lock:
            self._drain()  # queued before this SYNC: an older cycle's TPDOs are late, not fresh
            for i, msg in enumerate(self._rpdo_msgs):
                pack(msg.data, 0, controlwords[i], permille[i])
            self._cycle_no += 1
            cycle = self._cycle_no
            self._sync_counter = counter = fr.next_sync_counter(self._sync_counter)
            self._sync_msg.data[0] = counter
            self._pending = n * self._tpdos_per_drive
            self._open = True
            sync_time = time.monotonic()
            try:
                self._send_cycle_frames()
                deadline = sync_time + self.config.feedback_timeout_s
                monotonic = time.monotonic
                dispatch = self._dispatch
                recv = bus.recv
                while self._pending > 0:
                    remaining = deadline - monotonic()
                    if remaining <= 0:
                        break
                    try:
                        msg = recv(remaining)
                    except Exception as exc:  # noqa: BLE001 - any backend failure is a transport error
                        raise TransportError(f"receiving failed: {exc}") from exc
                    if msg is None:
                        break
                    dispatch(msg, monotonic())
            finally:
                self._open = False
            now = time.monotonic()
            if self._heartbeat_armed:
                self._check_heartbeats(now)
            got1 = self._got1
            got2 = self._got2
            statusword = self._statusword
            if self._fd:
                fresh = [g == cycle for g in got1]
                missing = fresh.count(False)
            else:
                fresh = [a == cycle and b == cycle for a, b in zip(got1, got2)]
                missing = 2 * n - got1.count(cycle) - got2.count(cycle)
            self._dropped += missing
            for i in range(n):
                if fresh[i]:
                    self._missed[i] = 0
                    self._states[i] = decode_statusword_fast(statusword[i])
                else:
                    self._missed[i] += 1
            position = self._position
            velocity = self._velocity
            torque_pm = self._torque_pm
            rx_time = self._rx_time
        self._last_cycle_end_s = now
        return DriveFeedback(
            cycle=cycle,
            sync_time_s=sync_time,
            position_rad=np.array(position, dtype=np.float64) / self._counts_per_rad,
            velocity_rad_s=np.array(velocity, dtype=np.float64) / self._counts_per_rad,
            torque_nm=np.array(torque_pm, dtype=np.float64) / self._permille_per_nm,
            commanded_torque_nm=np.array(commanded_nm, dtype=np.float64),
            fresh=np.array(fresh, dtype=bool),
            rx_time_s=np.array(rx_time, dtype=np.float64),
            states=tuple(self._states),
        )

    def _check_cycle(self, feedback: DriveFeedback) -> None:
        limit = self.config.max_missed_cycles
        timed_out = tuple(self.node_ids[i] for i, m in enumerate(self._missed) if m > limit)
        if timed_out:
            self._enabled = False
            raise FeedbackTimeoutError(timed_out, limit + 1)
        for i, state in enumerate(feedback.states):
            if not feedback.fresh[i] or state is State.OPERATION_ENABLED:
                continue
            self._enabled = False
            if state in _FAULT_STATES:
                raise DriveFaultError(self.node_ids[i], self._last_emcy[i], f"statusword says {state.value}")
            raise DriveStateError(f"drive {self.node_ids[i]} left operation enabled: {state.value}")

    def _stop_drives(self, controlword: int, targets: set[State]) -> tuple[State, ...]:
        self._enabled = False
        if self._bus is None:
            return tuple(self._states)
        deadline = time.monotonic() + self.config.state_change_timeout_s
        zeros = [0] * self.n_joints
        while True:
            try:
                feedback = self._cycle([controlword] * self.n_joints, zeros, self._zeros_nm)
            except DriveError as exc:  # the bus itself failed: nothing more to do here
                log.warning("stopping drives: %s", exc)
                return tuple(self._states)
            done = all(s in targets or s in _FAULT_STATES for s in feedback.states)
            if feedback.fresh.all() and done:
                return feedback.states
            if time.monotonic() > deadline:
                log.warning("drives did not confirm the stop: %s", self._describe_states())
                return tuple(self._states)

    # --- start-up --------------------------------------------------------------------------------

    def _boot_and_configure(self) -> None:
        timeout = self.config.state_change_timeout_s
        self._booted = [False] * self.n_joints
        for node_id in self.node_ids:
            self.nmt(fr.NmtCommand.RESET_COMMUNICATION, node_id)
        self._wait(lambda i: self._booted[i], timeout, "no boot-up message")
        for i, node in enumerate(self._nodes):
            self._configure(i, node)
        for node_id in self.node_ids:
            self.nmt(fr.NmtCommand.START, node_id)
        # Heartbeats were switched on by SDO (0x1017); the first one after START confirms it.
        self._wait(lambda i: self._nmt_state[i] is fr.NmtState.OPERATIONAL,
                   timeout + self.config.heartbeat_producer_ms / 1000, "not NMT operational")
        now = time.monotonic()
        self._last_heartbeat = [now] * self.n_joints
        self._heartbeat_lost = [False] * self.n_joints
        self._heartbeat_armed = True

    def _wait(self, done: object, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        check = done  # type: ignore[assignment]
        while True:
            missing = [self.node_ids[i] for i in range(self.n_joints) if not check(i)]  # type: ignore[operator]
            if not missing:
                return
            if self._errors and isinstance(self._errors[0], TransportError):
                raise self._errors.popleft()
            if time.monotonic() > deadline:
                raise DriveStateError(f"drive(s) {', '.join(map(str, missing))}: {what} within {timeout_s:g} s")
            time.sleep(0.0005)

    def _configure(self, i: int, node: canopen.RemoteNode) -> None:
        joint = self.config.joints[i]
        node_id = joint.node_id
        device_type = self.sdo_read_int(node_id, odx.DEVICE_TYPE)
        if device_type & 0xFFFF != 402:
            raise DriveConfigError(f"joints.{i}: drive {node_id} device type 0x{device_type:08X} is not CiA 402")
        modes = self.sdo_read_int(node_id, odx.SUPPORTED_MODES)
        if not modes & (1 << 9):
            raise DriveConfigError(f"joints.{i}: drive {node_id} does not support cyclic synchronous torque")
        increments = self.sdo_read_int(node_id, odx.ENCODER_RESOLUTION, 1)
        revolutions = self.sdo_read_int(node_id, odx.ENCODER_RESOLUTION, 2)
        if joint.encoder_counts_per_rev is not None and joint.encoder_counts_per_rev * revolutions != increments:
            raise DriveConfigError(
                f"joints.{i}.encoder_counts_per_rev: {joint.encoder_counts_per_rev} but drive {node_id} "
                f"reports {increments} increments per {revolutions} revolution(s)"
            )
        self._counts_per_rad[i] = counts_per_rad_from_resolution(increments, revolutions)
        self.sdo_write(node_id, odx.MODES_OF_OPERATION, 0, odx.MODE_CYCLIC_SYNC_TORQUE)
        self.sdo_write(node_id, odx.RATED_TORQUE, 0, joint.effective_rated_torque_mnm)
        self.sdo_write(node_id, odx.MAX_TORQUE, 0, joint.max_torque_permille)
        self.sdo_write(node_id, odx.QUICK_STOP_OPTION, 0, self.config.quick_stop_option)
        self.sdo_write(node_id, odx.HEARTBEAT_PRODUCER, 0, self.config.heartbeat_producer_ms)
        self.sdo_write(node_id, odx.SYNC_OVERFLOW, 0, odx.SYNC_COUNTER_MAX)  # SYNCs carry a counter
        self._map_pdo(node_id, odx.RPDO1_COMM, odx.RPDO1_MAP, fr.RPDO1_BASE + node_id, self._layout.rpdo1)
        self._map_pdo(node_id, odx.TPDO1_COMM, odx.TPDO1_MAP, fr.TPDO1_BASE + node_id, self._layout.tpdo1)
        self._map_pdo(node_id, odx.TPDO2_COMM, odx.TPDO2_MAP, fr.TPDO2_BASE + node_id, self._layout.tpdo2)
        display = self.sdo_read_int(node_id, odx.MODES_DISPLAY)
        if display != odx.MODE_CYCLIC_SYNC_TORQUE:
            raise DriveStateError(f"drive {node_id} runs mode {display}, not cyclic synchronous torque")

    def _map_pdo(self, node_id: int, comm: int, mapping: int, cob_id: int, entries: tuple[int, ...]) -> None:
        # CiA 301 order: invalidate the PDO, clear the count, write entries, set the count, validate.
        self.sdo_write(node_id, comm, 1, cob_id | odx.PDO_COB_ID_INVALID)
        if not entries:
            return  # stays disabled (TPDO2 with CAN FD)
        self.sdo_write(node_id, mapping, 0, 0)
        for k, entry in enumerate(entries, start=1):
            self.sdo_write(node_id, mapping, k, entry)
        self.sdo_write(node_id, mapping, 0, len(entries))
        self.sdo_write(node_id, comm, 2, odx.TRANSMISSION_SYNC_EVERY)
        self.sdo_write(node_id, comm, 1, cob_id)

    # --- receive thread --------------------------------------------------------------------------

    def _build_handlers(self) -> None:
        handlers: dict[int, object] = {}
        for i, node_id in enumerate(self.node_ids):
            if self._fd:
                handlers[fr.TPDO1_BASE + node_id] = (self._on_tpdo_fd, i)
            else:
                handlers[fr.TPDO1_BASE + node_id] = (self._on_tpdo1, i)
                handlers[fr.TPDO2_BASE + node_id] = (self._on_tpdo2, i)
            handlers[fr.HEARTBEAT_BASE + node_id] = (self._on_heartbeat, i)
            handlers[fr.EMCY_BASE + node_id] = (self._on_emcy, i)
            handlers[fr.SDO_TX_BASE + node_id] = (self._on_sdo, i)
        self._handlers = handlers

    def _rx_loop(self) -> None:
        bus = self._bus
        assert bus is not None
        monotonic = time.monotonic
        next_check = monotonic()
        while not self._stop.is_set():
            if self._caller_rx:
                # Cycles receive on the caller's thread; step in only when it has gone idle, and
                # never block in recv while holding the bus (the next cycle must not wait for us).
                self._wake.wait(_IDLE_POLL_S)
                self._wake.clear()
                if self._stop.is_set() or not self._caller_rx:
                    continue
                if monotonic() - self._last_cycle_end_s < _IDLE_TAKEOVER_S:
                    continue
                if not self._rx_lock.acquire(blocking=False):
                    continue
                try:
                    self._drain()
                    if self._heartbeat_armed:
                        self._check_heartbeats(monotonic())
                except TransportError as exc:
                    if not self._stop.is_set():
                        self._errors.append(exc)
                    return
                finally:
                    self._rx_lock.release()
                continue
            with self._rx_lock:
                try:
                    msg = bus.recv(_RX_POLL_S)
                except Exception as exc:  # noqa: BLE001 - any backend failure ends reception
                    if not self._stop.is_set():
                        self._errors.append(TransportError(f"receiving failed: {exc}"))
                    return
                now = monotonic()
                if msg is not None:
                    self._dispatch(msg, now)
            if now >= next_check:
                next_check = now + _RX_POLL_S
                if self._heartbeat_armed:
                    self._check_heartbeats(now)

    def _drain(self) -> None:
        """Under _rx_lock: handle every frame already queued, without waiting."""
        bus = self._bus
        assert bus is not None
        monotonic = time.monotonic
        while True:
            try:
                msg = bus.recv(0.0)
            except Exception as exc:  # noqa: BLE001 - any backend failure is a transport error
                raise TransportError(f"receiving failed: {exc}") from exc
            if msg is None:
                return
            self._dispatch(msg, monotonic())

    def _dispatch(self, msg: can.Message, now: float) -> None:
        self._received += 1
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            self._malformed += 1
            return
        entry = self._handlers.get(msg.arbitration_id)
        if entry is None:
            self._unknown += 1
            return
        handler, i = entry  # type: ignore[misc]
        try:
            handler(i, msg, now)
        except (fr.MalformedFrameError, ValueError):
            self._malformed += 1
        except Exception as exc:  # noqa: BLE001 - keep receiving, report once
            log.exception("frame handler failed")
            self._errors.append(TransportError(f"frame handler failed: {exc!r}"))

    @contextlib.contextmanager
    def _background_receive(self) -> Iterator[None]:
        """The background thread receives (blocking) meanwhile: canopen's SDO client waits for
        responses it routes."""
        previous = self._caller_rx
        self._caller_rx = False
        self._wake.set()
        try:
            yield
        finally:
            self._caller_rx = previous
            self._last_cycle_end_s = time.monotonic()

    def _accept(self, i: int, got: list[int]) -> bool:
        """Under _rx_lock: may this drive's frame count for the open cycle?"""
        if not self._open or got[i] == self._cycle_no:
            self._late += 1
            return False
        got[i] = self._cycle_no
        self._pending -= 1
        return True

    def _on_tpdo1(self, i: int, msg: can.Message, now: float) -> None:
        data = msg.data
        if len(data) != fr.TPDO1_LENGTH:
            raise fr.MalformedFrameError("TPDO1 length")
        statusword, torque, position = fr.unpack_tpdo1(data)
        if decode_statusword_fast(statusword) is State.UNKNOWN:
            raise fr.MalformedFrameError("statusword")
        if self._accept(i, self._got1):
            self._statusword[i] = statusword
            self._torque_pm[i] = torque
            self._position[i] = position
            self._rx_time[i] = now

    def _on_tpdo2(self, i: int, msg: can.Message, now: float) -> None:
        data = msg.data
        if len(data) != fr.TPDO2_LENGTH:
            raise fr.MalformedFrameError("TPDO2 length")
        (velocity,) = fr.unpack_tpdo2(data)
        if self._accept(i, self._got2):
            self._velocity[i] = velocity
            self._rx_time[i] = now

    def _on_tpdo_fd(self, i: int, msg: can.Message, now: float) -> None:
        data = msg.data
        if len(data) != fr.TPDO_FD_SYNC_LENGTH:
            raise fr.MalformedFrameError("FD TPDO length")
        statusword, torque, position, velocity, counter = fr.unpack_tpdo_fd_sync(data)
        if decode_statusword_fast(statusword) is State.UNKNOWN:
            raise fr.MalformedFrameError("statusword")
        if counter != self._sync_counter:  # answers an older SYNC: stale whenever it arrives
            self._late += 1
            return
        if self._accept(i, self._got1):
            self._statusword[i] = statusword
            self._torque_pm[i] = torque
            self._position[i] = position
            self._velocity[i] = velocity
            self._rx_time[i] = now

    def _on_heartbeat(self, i: int, msg: can.Message, now: float) -> None:
        state = fr.decode_heartbeat(bytes(msg.data))
        self._heartbeats += 1
        # When it was on the bus, not when a cycle got round to it: the transport's time stamp
        # (wall clock in every python-can backend) mapped onto the monotonic clock.
        seen = msg.timestamp + (now - time.time()) if msg.timestamp > 0 else now
        self._last_heartbeat[i] = min(now, seen)
        self._heartbeat_lost[i] = False
        previous = self._nmt_state[i]
        self._nmt_state[i] = fr.NmtState.PRE_OPERATIONAL if state is fr.NmtState.BOOT_UP else state
        if state is fr.NmtState.BOOT_UP:
            self._booted[i] = True
        if self._heartbeat_armed and state is not fr.NmtState.OPERATIONAL and previous is not state:
            what = "rebooted (boot-up message)" if state is fr.NmtState.BOOT_UP else f"NMT state {state.name}"
            self._errors.append(DriveStateError(f"drive {self.node_ids[i]}: {what}"))

    def _on_emcy(self, i: int, msg: can.Message, now: float) -> None:
        emcy = fr.decode_emcy(bytes(msg.data))
        self._emcy += 1
        if emcy.error_code == fr.EMCY_ERROR_RESET:
            self._last_emcy[i] = 0
            return
        self._last_emcy[i] = emcy.error_code
        self._errors.append(
            DriveFaultError(self.node_ids[i], emcy.error_code, f"EMCY, error register 0x{emcy.error_register:02X}")
        )

    def _on_sdo(self, i: int, msg: can.Message, now: float) -> None:
        if len(msg.data) != 8:
            raise fr.MalformedFrameError("SDO length")
        self._nodes[i].sdo.on_response(fr.SDO_TX_BASE + self.node_ids[i], bytes(msg.data), now)

    def _check_heartbeats(self, now: float) -> None:
        timeout = self.config.heartbeat_timeout_s
        for i, last in enumerate(self._last_heartbeat):
            if not self._heartbeat_lost[i] and now - last > timeout:
                self._heartbeat_lost[i] = True
                self._errors.append(HeartbeatLostError(self.node_ids[i], f"no heartbeat for {now - last:.3f} s"))

    # --- helpers ---------------------------------------------------------------------------------

    def _send_cycle_frames(self) -> None:
        """Every RPDO, then the SYNC: one batch where the transport has one (the bridge)."""
        bus = self._bus
        assert bus is not None
        msgs = self._cycle_msgs
        try:
            send_batch = getattr(bus, "send_batch", None)
            if send_batch is not None:
                send_batch(msgs)
            else:
                send = bus.send
                for msg in msgs:
                    send(msg)
        except (can.CanError, OSError) as exc:
            raise TransportError(f"sending the cycle's frames failed: {exc}") from exc
        self._sent += len(msgs)

    def _send(self, msg: can.Message) -> None:
        if self._bus is None:
            raise TransportError("bus is closed")
        try:
            self._bus.send(msg)
        except (can.CanError, OSError) as exc:
            raise TransportError(f"sending 0x{msg.arbitration_id:03X} failed: {exc}") from exc
        self._sent += 1

    def _raise_pending(self) -> None:
        if self._errors:
            error = self._errors.popleft()
            if isinstance(error, (DriveFaultError, HeartbeatLostError, DriveStateError, TransportError)):
                self._enabled = False
            raise error
        if self._connected and (self._rx_thread is None or not self._rx_thread.is_alive()):
            raise TransportError("the receive thread has stopped")

    def _require_connected(self) -> None:
        if not self._connected:
            raise DriveStateError("not connected: call connect() first")

    def _node(self, node_id: int) -> canopen.RemoteNode:
        for node in self._nodes:
            if node.id == node_id:
                return node
        raise DriveCommandError(f"node {node_id} is not on this drive bus (nodes {self.node_ids})")

    @staticmethod
    def _step_towards(state: State, target: State) -> int:
        if state in (State.UNKNOWN, State.NOT_READY_TO_SWITCH_ON):
            return _CW_SHUTDOWN
        controlword = next_controlword(state, target)
        return _CW_ENABLE if controlword is None else controlword

    def _describe_states(self) -> str:
        return ", ".join(f"drive {n}: {s.value}" for n, s in zip(self.node_ids, self._states))


def _od_variable(node: canopen.RemoteNode, index: int, subindex: int) -> ODVariable | None:
    return odx.lookup_variable(node.object_dictionary, index, subindex)
