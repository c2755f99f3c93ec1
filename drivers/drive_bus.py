"""The drive bus: what the runtime calls to run N CiA 402 joint drives in cyclic synchronous torque.

Transport-independent (any python-can bus from :mod:`drivers.transport`)::

    bus = DriveBus(config)          # frozen DriveBusConfig; refuses an over-budget bus load
    bus.connect()                   # NMT reset -> boot-up, SDO configuration, PDO mapping, NMT start
    bus.enable()                    # CiA 402 state machine to Operation Enabled
    while running:
        feedback = bus.exchange(torque_nm)   # RPDOs + SYNC out, TPDOs in: one control cycle
    bus.quick_stop() / bus.disable()
    bus.close()

:class:`DriveBus` is a thin composition of the protocol services, one module each (as canopen
has them), over one :class:`~drivers.node.DriveNode` record per drive:

- start-up: :mod:`drivers.nmt` (reset, boot-up, start), :mod:`drivers.sdo` (client),
  :mod:`drivers.profiles.p402` (device checks, mode, torque scale), :mod:`drivers.pdo` (mapping),
  :func:`drivers.supervision.configure_master_loss` (the drives stop on their own if we die);
- the cycle: :class:`drivers.pdo.CyclicExchange` with :class:`drivers.sync.SyncProducer`;
- supervision: the drives' heartbeats (:class:`drivers.nmt.HeartbeatConsumer`), EMCY
  (:mod:`drivers.emcy`), stale feedback and the fail-safe (:mod:`drivers.supervision`), and the
  master's own heartbeat (:class:`drivers.nmt.HeartbeatProducer`, ``master_heartbeat_ms``).

Frames go through :class:`drivers.network.DriveNetwork`: cycles receive on the caller's thread, a
background thread receives during start-up and SDO transfers and while the caller is idle, and
sends the master's heartbeat. Errors found by a receiving thread (heartbeat lost, EMCY,
transport failure) are queued and raised by the caller's next ``exchange``/``enable``.
Malformed frames, unknown COB-IDs, late and missing TPDOs never raise on their own: they are
counted (:attr:`DriveBus.counters`).

:meth:`exchange` is :class:`drivers.joint_bus.JointBusBase`'s: set-point checks, the missed-cycle
budget (``max_missed_cycles``), the drives' states and the fail-safe stop before any of
:data:`drivers.errors.FATAL_ERRORS` are written there once; this class adds the CANopen cycle
(:meth:`_cycle_internal`: quantisation with error feedback, RPDOs + SYNC out, TPDOs in).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence

import can
import numpy as np
from canopen.objectdictionary import ODVariable

from drivers.bus_guard import BusGuard, MasterPresentError, master_listen_s
from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx
from drivers.cia402.state_machine import State
from drivers.config import DriveBusConfig
from drivers.eds_check import check_bus, raise_first_error
from drivers.emcy import EmcyConsumer
from drivers.errors import FATAL_ERRORS, DriveError, DriveStateError, TransportError
from drivers.feedback import BusCounters, DriveFeedback
from drivers.joint_bus import JointBusBase, clip_torque
from drivers.network import DriveNetwork
from drivers.nmt import HeartbeatConsumer, HeartbeatProducer, send_command, wait_for
from drivers.node import DriveNode
from drivers.pdo import CyclicExchange, map_layout
from drivers.profiles import p402
from drivers.sdo import SdoClient
from drivers.supervision import configure_master_loss, fail_safe
from drivers.sync import SYNC_OVERFLOW_OBJECT, SyncProducer
from drivers.transport import open_bus

__all__ = ["BusCounters", "DriveBus", "DriveFeedback"]

log = logging.getLogger(__name__)

# The overlapped cycle's collect waits at most this share of a period for TPDOs not in yet: an
# answer later than that is treated as missing for this cycle (stale), never waited for.
COLLECT_GRACE = 0.5


class _Services:
    """The protocol services of one DriveBus, built at its first connect (they load the EDS)."""

    def __init__(
        self, config: DriveBusConfig, network: DriveNetwork, nodes: Sequence[DriveNode], sync: SyncProducer
    ) -> None:
        self.sdo = SdoClient(network, nodes, config.eds_path or odx.EDS_PATH, config.sdo_timeout_s)
        # SYNCs carry the counter when every drive takes 0x1019, or some drive echoes it (CAN FD).
        has_overflow = [self.sdo.variable(node.node_id, odx.SYNC_OVERFLOW, 0) is not None for node in nodes]
        sync.carry_counter(all(has_overflow) or any(node.fd_sync_echo for node in nodes))
        self.heartbeats = HeartbeatConsumer(network, nodes, config.heartbeat_timeout_s)
        self.emcy = EmcyConsumer(network, nodes)
        self.exchange = CyclicExchange(network, nodes, sync, config.feedback_timeout_s, config.transport.fd)
        self.master_heartbeat = HeartbeatProducer(network, config.master_node_id, config.master_heartbeat_ms / 1000)
        network.supervise = self.heartbeats.check
        network.produce = self.master_heartbeat.send_if_due
        tpdo_bases = (fr.TPDO1_BASE,) if config.transport.fd else (fr.TPDO1_BASE, fr.TPDO2_BASE)
        self.guard = BusGuard(
            network,
            config.node_ids,
            config.master_node_id,
            (base + node.node_id for base in tpdo_bases for node in nodes),
            config.heartbeat_producer_ms / 1000,
            lambda: self.exchange.cycle,
        )
        network.watch = self.guard.watch
        network.watch_frame = self.guard.watch_frame


class DriveBus(JointBusBase):
    """N CiA 402 drives in cyclic synchronous torque on one CAN bus. Not thread-safe: one caller."""

    def __init__(self, config: DriveBusConfig, bus: can.BusABC | None = None) -> None:
        """``bus``: an already open python-can bus to use (not closed by :meth:`close`)."""
        self.config = config
        self.bus_load = config.bus_load()  # raises BusLoadError before touching the bus
        # Every drive's EDS against what the runtime maps and writes, and the bus's COB-IDs:
        # DriveConfigError naming the file, node and object before anything is written to a drive.
        raise_first_error(check_bus(config))
        self._bus = bus
        self._owns_bus = bus is None
        self.nodes = tuple(DriveNode(i, joint, config.transport.fd) for i, joint in enumerate(config.joints))
        super().__init__(config.node_ids, [node.max_torque_nm for node in self.nodes], config.max_missed_cycles)
        self._permille_per_nm = np.array([node.permille_per_nm for node in self.nodes])
        self._network = DriveNetwork(bus)  # type: ignore[arg-type]  # bus set at connect when None
        self._sync = SyncProducer()
        self._services: _Services | None = None
        self._connected = False
        self._cw_enable = [p402.CW_ENABLE] * self.n_joints
        self._zeros_nm = np.zeros(self.n_joints)
        # Rounding errors of the last two set-points (exchange only), the older one carried into the
        # next set-point: see _setpoints.
        self._residual_nm = np.zeros((2, self.n_joints))

    # --- state -----------------------------------------------------------------------------------

    @property
    def counters(self) -> BusCounters:
        network, services = self._network, self._services
        if services is None:
            return BusCounters()
        return BusCounters(
            cycles=services.exchange.cycle,
            frames_sent=network.frames_sent,
            frames_received=network.frames_received,
            dropped=services.exchange.dropped,
            late=services.exchange.late,
            malformed=network.malformed,
            unknown_cob_id=network.unknown_cob_id,
            emcy=services.emcy.received,
            heartbeats=services.heartbeats.received,
        )

    @property
    def states(self) -> tuple[State, ...]:
        """CiA 402 state of each drive from its last TPDO."""
        return tuple(node.state for node in self.nodes)

    @property
    def counts_per_rad(self) -> np.ndarray:
        return np.array([node.counts_per_rad for node in self.nodes])

    @property
    def sync_counter(self) -> int:
        """Counter byte of the last SYNC sent (1..240; 0 before the first)."""
        return self._sync.counter

    # --- start-up --------------------------------------------------------------------------------

    def connect(self) -> None:
        """Open the bus, reset and configure every drive by SDO, start them (NMT operational)."""
        if self._connected:
            return
        if self._bus is None:
            self._bus = open_bus(self.config.transport)
        network = self._network
        network.bus = self._bus
        try:
            if self._services is None:
                self._services = _Services(self.config, network, self.nodes, self._sync)
            network.start()
            self._services.guard.forget_senders()
            self._services.guard.check_no_master(master_listen_s(self.config))  # before our first frame
            self._services.master_heartbeat.start()
            self._start_up(self._services)
            self._services.guard.arm()
        except MasterPresentError:
            self._close(stop_drives=False)  # not ours: not a single frame to another master's drives
            raise
        except BaseException:
            self.close()
            raise
        self._services.exchange.refresh_scaling()
        self._permille_per_nm = np.array([node.permille_per_nm for node in self.nodes])  # as read at start-up
        self._connected = True
        network.last_cycle_end_s = time.monotonic()
        network.caller_receives = True

    def _start_up(self, services: _Services) -> None:
        config, network, nodes, sdo = self.config, self._network, self.nodes, services.sdo
        timeout = config.state_change_timeout_s
        for node in nodes:
            node.booted = False
        for node in nodes:
            send_command(network, fr.NmtCommand.RESET_COMMUNICATION, node.node_id)
        wait_for(network, nodes, lambda node: node.booted, timeout, "no boot-up message")
        for node in nodes:
            p402.configure(sdo, node, config)
            sdo.write(node.node_id, odx.HEARTBEAT_PRODUCER, 0, config.heartbeat_producer_ms)
            if sdo.variable(node.node_id, odx.SYNC_OVERFLOW, 0) is not None:
                sdo.write(node.node_id, *SYNC_OVERFLOW_OBJECT)  # SYNCs carry a counter
            configure_master_loss(sdo, node, config)
            map_layout(sdo, node, services.exchange.layout_for(node))
            p402.check_mode(sdo, node)
        for node in nodes:
            send_command(network, fr.NmtCommand.START, node.node_id)
        # Heartbeats were switched on by SDO (0x1017); the first one after START confirms it.
        wait_for(
            network,
            nodes,
            lambda node: node.nmt_state is fr.NmtState.OPERATIONAL,
            timeout + config.heartbeat_producer_ms / 1000,
            "not NMT operational",
        )
        services.heartbeats.arm()

    # --- the cycle -------------------------------------------------------------------------------

    def _cycle(self, controlwords: Sequence[int], permille: Sequence[int], commanded_nm: np.ndarray) -> DriveFeedback:
        return self._exchange_service().run(controlwords, permille, commanded_nm)

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
            permille, commanded = self._quantised(self._checked_setpoint(hold_torque_nm, "hold_torque_nm"))
        feedback = p402.walk_to_enabled(
            self._cycle, self.nodes, permille, commanded, self.config.state_change_timeout_s, self._raise_pending
        )
        self._reset_supervision()
        self._residual_nm[:] = 0.0
        self._enabled = True
        return feedback

    def _cycle_internal(self, setpoint_nm: np.ndarray) -> DriveFeedback:
        """One control cycle on the bus (see :meth:`_quantised` for what is sent)."""
        permille, commanded = self._quantised(setpoint_nm, carry=True)
        return self._cycle(self._cw_enable, permille, commanded)

    def _send_internal(self, setpoint_nm: np.ndarray) -> None:
        permille, commanded = self._quantised(setpoint_nm, carry=True)
        self._exchange_service().begin(self._cw_enable, permille, commanded)

    def _collect_internal(self) -> DriveFeedback:
        """This SYNC's TPDOs: what came in meanwhile, then at most ``COLLECT_GRACE`` of a period
        for the rest (not later than the feedback timeout); a TPDO after that is late."""
        exchange = self._exchange_service()
        grace_s = COLLECT_GRACE * self.config.period_s
        deadline = min(exchange.sync_time_s + self.config.feedback_timeout_s, time.monotonic() + grace_s)
        return exchange.finish(deadline)

    def _exchange_service(self) -> CyclicExchange:
        services = self._services
        if services is None or self._network.bus is None:
            raise TransportError("bus is closed")
        return services.exchange

    def _quantised(self, wanted_nm: np.ndarray, carry: bool = False) -> tuple[list[int], np.ndarray]:
        """(‰ of rated torque per drive, the torque in N·m those stand for) of a clipped set-point.

        Set-points are quantised to 1 ‰ of each drive's rated torque. With ``carry`` (exchange
        only) each cycle's rounding error is added to the set-point two cycles later (error
        feedback with the noise transfer 1 - z⁻², |error| <= half a step each): the torque's
        running average is the one asked for, never biased by up to half a step (a law with
        little static stiffness integrates a bias into a drift: H∞ moved 5° RMS from the
        simulation with plain rounding), and no rounding noise lands at the Nyquist frequency,
        where a light joint's discrete loop is least damped (carrying into the next cycle,
        1 - z⁻¹, doubled it there and drove MRAC's wrist 3 over its velocity limit). docs/hil.md
        has the figures. ``commanded_torque_nm`` in the feedback is what was actually sent.
        """
        wanted = wanted_nm
        if carry:
            wanted = wanted + self._residual_nm[1]  # the carried error never takes it past the limit:
            limit = self._max_torque_list  # the stack's one clip (drivers.joint_bus.clip_torque)
            clip_torque(wanted, wanted.tolist(), limit, limit, wanted)
        permille = np.rint(wanted * self._permille_per_nm)
        sent = permille / self._permille_per_nm
        if carry:
            self._residual_nm[1] = self._residual_nm[0]
            self._residual_nm[0] = wanted - sent
        return permille.astype(np.int64).tolist(), sent

    def _fail_safe(self) -> None:
        if self._connected:
            fail_safe(self._cycle, self.nodes)

    def _last_emcy_code(self, joint: int) -> int:
        return self.nodes[joint].last_emcy_code

    # --- stopping --------------------------------------------------------------------------------

    def quick_stop(self) -> tuple[State, ...]:
        """Quick stop every drive (zero torque, brake); best effort, never raises for drive faults.

        Returns the states reached (Quick Stop Active or Switch On Disabled, per 0x605A).
        """
        return self._stop_drives(p402.CW_QUICK_STOP, p402.QUICK_STOP_STATES)

    def disable(self) -> tuple[State, ...]:
        """Disable voltage on every drive (Switch On Disabled: brake holds). Best effort."""
        return self._stop_drives(p402.CW_DISABLE_VOLTAGE, frozenset({State.SWITCH_ON_DISABLED}))

    def _stop_drives(self, controlword: int, targets: frozenset[State]) -> tuple[State, ...]:
        self._enabled = False
        if self._network.bus is None or self._services is None:
            return self.states
        return p402.stop(self._cycle, self.nodes, controlword, targets, self.config.state_change_timeout_s)

    def fault_reset(self) -> None:
        """Reset faulted drives to Switch On Disabled (rising edge of controlword bit 7)."""
        self._require_connected()
        self._network.errors.clear()
        p402.fault_reset(self._cycle, self.nodes, self.config.state_change_timeout_s)
        self._network.errors.clear()  # EMCY "error reset" frames may have been queued as errors

    def close(self) -> None:
        """Disable the drives if enabled, stop their PDOs (NMT pre-operational), release the bus.
        Never raises for a failing bus: what stopped the run is the error the caller sees."""
        self._close(stop_drives=True)

    def _close(self, stop_drives: bool) -> None:
        if self._enabled:
            try:
                self.disable()
            except DriveError as exc:
                log.warning("disable on close failed: %s", exc)
        self._enabled = False
        network, services = self._network, self._services
        if network.bus is not None and network.receiving and stop_drives:
            if services is not None:
                services.heartbeats.armed = False
            for node_id in self.node_ids:
                try:
                    self.nmt(fr.NmtCommand.ENTER_PRE_OPERATIONAL, node_id)
                except DriveError:
                    break
        if services is not None:
            services.master_heartbeat.stop()
        network.stop()
        if self._owns_bus and self._bus is not None:
            try:
                self._bus.shutdown()
            except Exception as exc:  # noqa: BLE001 - a dead peer must not mask the first error
                log.warning("closing the bus failed: %s", exc)
            self._bus = None
            network.bus = None  # type: ignore[assignment]  # canopen types it BusABC; None detaches the bus
        self._connected = False

    def __enter__(self) -> DriveBus:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- SDO and NMT (start-up and diagnostics) ----------------------------------------------------

    def sdo_read(self, node_id: int, index: int, subindex: int = 0) -> bytes:
        """Read an object by SDO (start-up and diagnostics; not for the control loop)."""
        return self._sdo().read(node_id, index, subindex)

    def sdo_write(self, node_id: int, index: int, subindex: int, value: int | bytes) -> None:
        """Write an object by SDO; an int is encoded with the EDS data type of the object."""
        self._sdo().write(node_id, index, subindex, value)

    def sdo_read_int(self, node_id: int, index: int, subindex: int = 0) -> int:
        return self._sdo().read_int(node_id, index, subindex)

    def sdo_variable(self, node_id: int, index: int, subindex: int = 0) -> ODVariable | None:
        """The drive's EDS entry of an object (None: not in its dictionary)."""
        return self._sdo().variable(node_id, index, subindex)

    def layout_for(self, node: DriveNode) -> odx.PdoLayout:
        """The PDO layout mapped on ``node`` at start-up."""
        if self._services is None:
            raise DriveStateError("not connected: call connect() first")
        return self._services.exchange.layout_for(node)

    def nmt(self, command: fr.NmtCommand, node_id: int = 0) -> None:
        if self._network.bus is None:
            raise TransportError("bus is closed")
        send_command(self._network, command, node_id)

    # --- helpers ---------------------------------------------------------------------------------

    def _sdo(self) -> SdoClient:
        if self._services is None or self._network.bus is None:
            raise DriveStateError("not connected: call connect() first")
        return self._services.sdo

    def _raise_pending(self) -> None:
        errors = self._network.errors
        if errors:
            error = errors.popleft()
            if isinstance(error, FATAL_ERRORS):
                self._enabled = False
            raise error
        if self._connected and not self._network.receiving:
            raise TransportError("the receive thread has stopped")

    def _require_connected(self) -> None:
        if not self._connected:
            raise DriveStateError("not connected: call connect() first")
