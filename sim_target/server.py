"""The target process: the pybullet plant behind the emulated CiA 402 drives.

Two clocks:

- ``lockstep``: every SYNC the drives receive advances physics by exactly one control period, with
  the torques latched at that SYNC, then the drives send their TPDOs with the new state. A HIL run
  is then deterministic and comparable with the pure simulation.
- ``realtime``: physics advances one period per tick of a monotonic clock with absolute deadlines
  (``next += period``); a late tick is counted and the missed periods skipped, never run in a
  burst. A SYNC then answers with the latest state. Lateness (late ticks, skipped periods, worst
  lag) is counted per run and in the status (sim_target/lateness.py); a run whose plant fell
  behind is invalid.

One thread does everything, in both clocks: it serves the drives' bus (``drives.serve_until``)
until the next physics deadline and steps the plant itself, so physics and drives never hand off
through a lock. Other threads (the control socket) only post faults and run starts on queues and
read the status snapshot. With ``clock: realtime`` that thread takes SCHED_FIFO, its CPU and
mlockall (``realtime:`` in the config; sim_target/rt_settings.py), and at start-up the target
times its own physics step and warns, on one line, when it cannot keep the period.

Faults: the plant's own (encoder noise, payload, torque impulse) are applied here; frame faults and
drive faults go to the drive layer's hooks. They come from the config file (scheduled at ``at_s``
simulated seconds) or, at run time, from a Unix control socket (``control_socket`` in the config):
one JSON object per line, the same schema as a config fault, e.g.::

    echo '{"kind": "payload", "mass_kg": 2.0}' | socat - UNIX-CONNECT:/run/hil/target.sock
    hil target inject --socket /run/hil/target.sock '{"kind": "impulse", "duration_s": 0.001}'
    hil target inject --socket /run/hil/target.sock '{"kind": "status"}'
    {"kind": "start", "position_rad": [...], "velocity_rad_s": [...], "faults": [...]}   # RunStart

Each line is answered with one JSON line: ``{"ok": true, ...}`` or ``{"ok": false, "error": ...}``.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np

from drivers.transport import BridgeServer, open_bus, start_bridge_server
from sim_target.config import (
    EncoderNoiseFault,
    Fault,
    HeartbeatFault,
    ImpulseFault,
    PayloadFault,
    RunStart,
    TargetConfig,
    TargetConfigError,
    TargetLayout,
    check_fault,
    check_run_start,
    target_layout,
)
from sim_target.control import ControlServer, send_control  # noqa: F401 - send_control re-exported
from sim_target.drive_bank import DriveBank
from sim_target.lateness import Lateness
from sim_target.plant import PybulletPlant, TorqueImpulse
from sim_target.plant_factory import make_plant
from sim_target.plant_protocol import JointState
from sim_target.rt_settings import start_lockstep, start_realtime

log = logging.getLogger(__name__)


@dataclass
class ServerStats:
    steps: int = 0
    syncs: int = 0
    late_ticks: int = 0  # realtime: ticks whose step ran past the next deadline (since start)
    skipped_periods: int = 0  # realtime: periods dropped to catch up, never run in a burst
    worst_lag_s: float = 0.0  # realtime: the latest a tick started after its deadline
    faults_applied: int = 0
    runs_started: int = 0  # RunStart placements done (start_run)


_LOCKSTEP_WAKE_S = 0.05  # lock-step: the loop thread looks at the fault queue at least this often
# Real time, with a master's SYNCs flowing, each period's physics tick runs right after the answer
# to the SYNC it belongs to, as a CiA 402 drive samples its feedback at the SYNC and answers at
# once: the physics of the period (with the torque latched at that SYNC) then never stands between
# a SYNC and its answer (measured: a tick a quarter period after the SYNC was still running when
# the next SYNC came in 77 % of the cycles of a 1 kHz master, 185 µs median added to its exchange).
# The ticks stay on the wall clock: a SYNC runs the tick only when it is due within
# ``_SYNC_GRACE`` of a period (earlier or later), a due tick waits that long for its SYNC and then
# runs on the clock alone (a late or silent master), and each SYNC pulls the tick's phase towards
# the SYNC (TargetServer._lock_phase_to_sync): a quarter of the error per SYNC, at most an eighth
# of a period (SYNC jitter is filtered, never a burst of ticks).
_TICK_AFTER_SYNC = 0.0
_SYNC_GRACE = 0.5
_SYNC_FLOWING_PERIODS = 2.0  # SYNCs flow while the last one is at most this many periods old
_PHASE_GAIN = 0.25
_MAX_PHASE_STEP = 0.125


class TargetServer:
    """Owns the plant, the drives and their bus; runs one of the two clocks until stopped."""

    def __init__(self, config: TargetConfig, plant: PybulletPlant, drives: DriveBank) -> None:
        self.config = config
        self.plant = plant
        self.drives = drives
        self.stats = ServerStats()
        self.lateness = Lateness.starting_now()  # this run's (since the last run start)
        self.realtime_settings: dict[str, Any] = {}  # applied/refused, the start-up cost probe
        self._period_s = config.period_s
        self._tick_after_sync_s = _TICK_AFTER_SYNC * config.period_s
        self._max_phase_step_s = _MAX_PHASE_STEP * config.period_s
        self._stop = threading.Event()
        self._pending: queue.SimpleQueue[Fault] = queue.SimpleQueue()
        self._starts: queue.SimpleQueue[RunStart] = queue.SimpleQueue()
        self._scheduled: list[Fault] = []
        self.layout = TargetLayout(
            plant.joint_names,
            tuple(plant.position_limit_rad[:, 0]),
            tuple(plant.position_limit_rad[:, 1]),
            config.drives.node_ids or tuple(range(1, plant.n_joints + 1)),
            *_urdf_limits(config, plant.joint_names),
        )
        for i, fault in enumerate(config.faults):
            check_fault(fault, self.layout, f"faults[{i}]")
            if isinstance(fault, ImpulseFault):  # the plant schedules impulses to the sub-period
                self.plant.add_impulse(TorqueImpulse(fault.torque_nm, fault.at_s, fault.duration_s))
                log.info("fault scheduled at t=%.4f s: %s", fault.at_s, fault)
            else:
                self._scheduled.append(fault)
        self._scheduled.sort(key=lambda fault: fault.at_s)
        self._start: RunStart | None = None  # armed by start_run, placed at the first enabled step
        self._control: ControlServer | None = None
        self.bridge_url: str | None = None  # ws://127.0.0.1:PORT/ when the bus is served (build_server)
        self._snapshot: tuple[Any, ...] = ()
        self._deadline_s = 0.0  # real time: the next physics tick (time.monotonic())
        self._last_sync_s = -math.inf  # real time: when the last SYNC was handled
        self._sync_waiting = False  # real time: a SYNC was answered and its tick not yet decided
        # The hot path's optional halves (tests stand in for plant and drives without them).
        self._plant_inputs = getattr(drives, "plant_inputs", None)
        self._advance = getattr(plant, "advance", None)
        measured, publish = getattr(plant, "measured_floats", None), getattr(drives, "publish_floats", None)
        self._float_feedback = (measured, publish) if measured is not None and publish is not None else None
        self._publish_snapshot()
        drives.set_sync_handler(self._on_sync)

    # --- clocks ---------------------------------------------------------------------------------

    def _on_sync(self) -> None:
        self.stats.syncs += 1
        if self.config.clock == "lockstep":
            self._step()
            self._publish_snapshot()
            return
        sync_s = time.monotonic()
        self._last_sync_s = sync_s
        self._sync_waiting = True
        self._lock_phase_to_sync(sync_s)
        self._take_pending()
        if self._start is not None and np.asarray(self.drives.operation_enabled(), dtype=bool).all():
            # Placed at the SYNC that finds every drive enabled, and that SYNC answered with the
            # placed state (as in lock-step): the master's first torque is computed on it, not on
            # the pose the arm had before (a saturated torque on the placed arm, 2 ms to a fault).
            self.drives.publish_feedback(self._place(self._start))
            return
        self._publish_plant_state()

    def _publish_plant_state(self) -> None:
        """The plant's last measurement to the drives: its plain floats where both sides offer
        them (the pybullet plant, the emulated drives: no array, no JointState per period)."""
        if self._float_feedback is not None:
            measured, publish = self._float_feedback
            publish(measured())
        else:
            self.drives.publish_feedback(self.plant.state())

    def _lock_phase_to_sync(self, sync_s: float) -> None:
        """Real time: move the next physics tick towards ``_TICK_AFTER_SYNC`` of a period after
        this SYNC (at it: the tick runs right after the answer), a bounded step per SYNC (a PLL, as
        a CiA 402 drive synchronises its cycle to SYNC). (Whatever the phase, a torque latched at
        one SYNC is integrated over the next period: one period from a sample to the torque
        computed from it, as with a real cyclic drive, where lock-step has none.) The tick rate
        stays the master's, i.e. the wall clock's; without SYNCs the ticks run on at their own
        period."""
        period_s = self._period_s
        half_s = 0.5 * period_s
        error_s = (self._deadline_s - sync_s - self._tick_after_sync_s + half_s) % period_s - half_s  # (-T/2, T/2]
        step_s = _PHASE_GAIN * error_s
        max_step_s = self._max_phase_step_s
        self._deadline_s -= max_step_s if step_s > max_step_s else (-max_step_s if step_s < -max_step_s else step_s)

    def _step(self) -> None:
        """One period of physics, its state published to the drives."""
        self._take_pending()
        self._apply_due_faults()
        # A joint whose drive is not enabled is braked: the plant applies no motor torque to it.
        if self._plant_inputs is not None:  # the emulated drives' one pass, the plant's floats
            torque_nm, braked = self._plant_inputs()
            if self._advance is not None:
                self._advance(torque_nm, braked)
            else:
                self.plant.step(torque_nm, braked)
            all_enabled = not any(braked)
        else:
            enabled = np.asarray(self.drives.operation_enabled(), dtype=bool)
            self.plant.step(self.drives.commanded_torque_nm(), ~enabled)
            all_enabled = bool(enabled.all())
        self.stats.steps += 1
        if self._start is not None and all_enabled:
            self.drives.publish_feedback(self._place(self._start))
            return
        self._publish_plant_state()

    # --- runs that start where a simulation starts ------------------------------------------------

    def start_run(self, start: RunStart) -> None:
        """Arm a run start (thread-safe; checked first): see :class:`sim_target.config.RunStart`."""
        check_run_start(start, self.layout, "start")
        self._starts.put(start)  # taken by the loop thread before its next step

    def _place(self, start: RunStart) -> JointState:
        self._start = None
        state = self.plant.reset(start.position_rad, start.velocity_rad_s)
        self.plant.clear_impulses()
        self._scheduled = []
        for fault in start.faults:
            if isinstance(fault, ImpulseFault):
                self.plant.add_impulse(TorqueImpulse(fault.torque_nm, fault.at_s, fault.duration_s))
            else:
                self._scheduled.append(fault)
        self._scheduled.sort(key=lambda fault: fault.at_s)
        self.stats.runs_started += 1
        self.lateness = Lateness.starting_now()  # a run's validity counts from its own start
        log.info(
            "run started at %s rad (time 0), %d fault(s) scheduled",
            np.round(state.position_rad, 4).tolist(),
            len(start.faults),
        )
        return state

    def run(self) -> None:
        """Serve until :meth:`stop` (or a signal handler calling it); then drives to a safe state."""
        try:
            if self.config.clock == "realtime":
                self._apply_realtime_settings()
                self._run_realtime()
            else:
                if self.config.realtime.in_lockstep:
                    self._apply_lockstep_settings()
                while not self._stop.is_set():  # the SYNC handler steps the plant, on this thread
                    self.drives.serve_until(time.monotonic() + _LOCKSTEP_WAKE_S)
                    self._publish_snapshot()
        finally:
            self.shutdown()

    def _run_realtime(self) -> None:
        """Ticks on the wall clock, each run right after its SYNC's answer while SYNCs flow (see
        ``_SYNC_GRACE``); a tick that cannot run within the grace is late, the periods wholly past
        are skipped (counted), never run in a burst."""
        period_s = self.config.period_s
        grace_s = _SYNC_GRACE * period_s
        flowing_s = _SYNC_FLOWING_PERIODS * period_s
        monotonic = time.monotonic
        stats = self.stats
        self._deadline_s = monotonic() + period_s
        while not self._stop.is_set():
            # SYNCs meanwhile are answered with the latest state; each may move the deadline.
            wait_s = grace_s if monotonic() - self._last_sync_s < flowing_s else 0.0
            self.drives.serve_until(self._deadline_s + wait_s, return_on_sync=True)
            if self._stop.is_set():
                break
            started_s = monotonic()
            if self._sync_waiting:  # a SYNC was just answered: its tick, if due within the grace
                self._sync_waiting = False
                if self._deadline_s - started_s > grace_s:
                    continue  # this period's tick ran already (at an earlier SYNC or on the clock)
            elif started_s < self._deadline_s + wait_s:
                continue
            tick_s = self._deadline_s
            self._step()
            deadline_s = tick_s + period_s
            now_s = monotonic()
            missed = 0
            # Overran past the next tick (and, while SYNCs flow, its grace): skip, never burst.
            slack_s = grace_s if now_s - self._last_sync_s < flowing_s else 0.0
            if now_s > deadline_s + slack_s:
                missed = int((now_s - deadline_s - slack_s) // period_s) + 1
                deadline_s += missed * period_s
                stats.late_ticks += 1
                stats.skipped_periods += missed
            self._deadline_s = deadline_s
            lag_s = max(0.0, started_s - tick_s)  # a tick run early at its SYNC is not late
            stats.worst_lag_s = max(stats.worst_lag_s, lag_s)
            self.lateness.tick(lag_s, missed)
            if stats.steps % 16 == 0:
                self._publish_snapshot()

    def _take_pending(self) -> None:
        if self._starts.empty():  # the common case, without raising queue.Empty every period
            return
        while True:
            try:
                self._start = self._starts.get_nowait()
            except queue.Empty:
                return

    def _apply_realtime_settings(self) -> None:
        """The start-up cost probe and warning, then this thread's real-time settings."""
        control_id = None if self._control is None else self._control.native_thread_id
        self.realtime_settings = start_realtime(self.plant, self.config, control_id)
        self._publish_snapshot()

    def _apply_lockstep_settings(self) -> None:
        control_id = None if self._control is None else self._control.native_thread_id
        self.realtime_settings = start_lockstep(self.config, control_id)
        self._publish_snapshot()

    def stop(self) -> None:
        self._stop.set()

    def shutdown(self) -> None:
        if self._control is not None:
            self._control.close()
            self._control = None
        try:
            self.drives.safe_stop()
        finally:
            self.drives.close()
            self.plant.close()

    # --- faults ---------------------------------------------------------------------------------

    def inject(self, fault: Fault) -> None:
        """Apply ``fault`` before the next step (thread-safe; from the control socket).

        Checked completely first (joint count, node ids): a fault accepted here cannot fail later
        in the physics thread and take the target down; TargetConfigError otherwise."""
        check_fault(fault, self.layout, "control")
        self._pending.put(fault)

    def _apply_due_faults(self) -> None:
        self._apply_pending()
        while self._scheduled and self._scheduled[0].at_s <= self.plant.time_s + 1e-12:
            self._apply(self._scheduled.pop(0), at_s=self.plant.time_s)

    def _apply_pending(self) -> None:
        if self._pending.empty():
            return
        while True:
            try:
                fault = self._pending.get_nowait()
            except queue.Empty:
                return
            self._apply(fault, at_s=self.plant.time_s)

    def _apply(self, fault: Fault, at_s: float) -> None:
        if isinstance(fault, EncoderNoiseFault):
            self.plant.set_encoder_noise(fault.position_rad, fault.velocity_rad_s)
        elif isinstance(fault, PayloadFault):
            self.plant.set_payload(fault.mass_kg, fault.inertia_kg_m2)
        elif isinstance(fault, ImpulseFault):
            self.plant.add_impulse(TorqueImpulse(fault.torque_nm, at_s, fault.duration_s))
        elif isinstance(fault, HeartbeatFault):
            self.drives.silence_heartbeat(fault.node_id, fault.silent)
        else:
            self.drives.apply_fault(fault)
        self.stats.faults_applied += 1
        log.info("fault applied at t=%.4f s: %s", at_s, fault)

    def _publish_snapshot(self) -> None:
        """What :meth:`status` answers, taken on the loop thread (the only one touching pybullet
        and the drives) and swapped in whole: a reader never sees half an update, never blocks it.
        Only references and small copies here (it runs before a lock-step SYNC's TPDOs); the
        control thread formats them."""
        lateness = self.lateness.as_dict(self.config.period_s) if self.config.clock == "realtime" else None
        self._snapshot = (
            self.plant.state(),  # immutable: a new JointState each period
            np.asarray(self.drives.operation_enabled()).copy(),
            self.plant.payload_kg,
            dict(self.stats.__dict__),
            lateness,
            dict(self.realtime_settings),
        )

    def status(self) -> dict[str, Any]:
        """The latest snapshot (at most 16 periods old in real time, 50 ms in lock-step)."""
        state, enabled, payload_kg, stats, lateness, realtime = self._snapshot
        return {
            "time_s": state.time_s,
            "position_rad": state.position_rad.round(6).tolist(),
            "operation_enabled": enabled.tolist(),
            "payload_kg": payload_kg,
            **stats,
            "clock": self.config.clock,
            "period_s": self.config.period_s,
            "substeps": self.plant.substeps,
            "lateness": lateness,
            "realtime": realtime,
        }

    # --- control socket -------------------------------------------------------------------------

    def serve_control(self, path: Path) -> None:
        self._control = ControlServer(path, self)


# --- assembly -------------------------------------------------------------------------------------


def _urdf_limits(
    config: TargetConfig, joint_names: tuple[str, ...]
) -> tuple[tuple[float, ...] | None, tuple[float, ...] | None]:
    """The URDF's effort and velocity limits of the plant's joints (None when not readable)."""
    try:
        layout = target_layout(config)
    except TargetConfigError:
        return None, None
    if layout.effort_nm is None or layout.velocity_limit_rad_s is None:
        return None, None
    effort = dict(zip(layout.joint_names, layout.effort_nm, strict=True))
    velocity = dict(zip(layout.joint_names, layout.velocity_limit_rad_s, strict=True))
    if any(name not in effort for name in joint_names):
        return None, None
    return tuple(effort[n] for n in joint_names), tuple(velocity[n] for n in joint_names)


def make_drives(config: TargetConfig, bus: can.BusABC, n_joints: int) -> DriveBank:
    """The emulated drives of sim_target/drives.py, configured from ``config.drives``."""
    from sim_target import drives as drive_module

    node_ids = config.drives.node_ids or tuple(range(1, n_joints + 1))
    if len(node_ids) != n_joints:
        raise TargetConfigError(f"drives.node_ids: {len(node_ids)} ids for {n_joints} joints")
    return drive_module.make_drive_bank(bus, node_ids, config, own_thread=False)  # served by run()


def build_server(config: TargetConfig, can_log: Path | None = None) -> tuple[TargetServer, Callable[[], None]]:
    """Plant, bus (and bridge), drives and control socket; returns the server and a closer.
    ``can_log``: every frame the drives send or receive also goes to this capture (docs/formats.md)."""
    plant = make_plant(config)
    bridge: BridgeServer | None = None
    try:
        if config.bridge is not None:
            bridge = start_bridge_server(config.bridge.host, config.bridge.port, config.bus.channel)
        bus = open_bus(config.bus)
        if can_log is not None:
            from drivers.capture import CanCapture, CaptureBus

            bus = CaptureBus(bus, CanCapture(can_log))
        try:
            drives = make_drives(config, bus, plant.n_joints)
        except Exception:
            bus.shutdown()
            raise
        server = TargetServer(config, plant, drives)
    except Exception:
        plant.close()
        if bridge is not None:
            bridge.close()
        raise
    if bridge is not None:
        server.bridge_url = bridge.url

    def close() -> None:
        bus.shutdown()
        if bridge is not None:
            bridge.close()

    if config.control_socket is not None:
        try:
            server.serve_control(config.control_socket)
        except BaseException:
            server.shutdown()
            close()
            raise

    return server, close
