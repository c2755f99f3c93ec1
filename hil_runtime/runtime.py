"""The runtime: lifecycle + pacer + bus + reference + controller + supervisor + telemetry, one loop.

A library first, the daemon second (``hil run`` wraps it, :mod:`hil_runtime.daemon`)::

    runtime = Runtime(config, bus)                 # bundle + conditions loaded and checked, no I/O
    runtime.configure()                            # UNCONFIGURED -> INACTIVE: bus up, policy warm
    runtime.activate()                             # INACTIVE -> ACTIVE: drives enabled, ramp built
    result = runtime.run(max_cycles=5000)          # the loop, on the calling thread
    runtime.record.arrays()                        # t_s, q, qd, q_ref, qd_ref, tau, tau_fb, fallback
    runtime.shutdown()                             # quick stop, disable, close: FINALIZED

Per cycle (ACTIVE), on one thread (:mod:`hil_runtime.loop`, the loop apart from this lifecycle):

    pacer.wait ─▶ overrun budget ─▶ bus.exchange(set-points) ─▶ supervisor.check_feedback ─▶ reference row
        ─▶ controller.step (one onnxruntime call) ─▶ supervisor.select_torque ─▶ next set-points
        ─▶ telemetry.offer_state (bounded, never blocks) ─▶ record ─▶ watchdog ping (sd_notify)

The set-points computed from cycle k's feedback go out with cycle k+1's SYNC: a lock-stepped
target then advances exactly one period under them, as the models simulator's zero-order hold.
Any fault (a driver error, which the driver raises after quick-stopping the drives; a supervisor
rule; an unexpected exception) quick-stops the drives and enters FAULT: the loop thread stays up,
keeps the watchdog fed, reports why, and waits for :meth:`request_reset` or :meth:`request_stop`.

:meth:`request_stop`, :meth:`request_reset` and :meth:`request_activate` only set flags the loop
reads: any thread (signal handler, control socket, Zenoh queryable) may call them.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.errors import DriveError
from drivers.joint_bus import JointBus
from hil_runtime.bundle import BundleError, PolicyBundle
from hil_runtime.conditions import ConditionError
from hil_runtime.config import RuntimeConfig, RuntimeConfigError
from hil_runtime.controller import Controller
from hil_runtime.lifecycle import Lifecycle, LifecycleError, LifecycleState, Transition
from hil_runtime.loading import condition_for, load_bundle_for, safety_limits_for
from hil_runtime.loop import ActiveLoop, CyclePipeline
from hil_runtime.pacer import Pacer
from hil_runtime.realtime import (
    RealtimeReport,
    clock_pacing_risk,
    freeze_heap,
    keep_other_threads_off,
    set_thread_affinity,
    set_thread_fifo,
)
from hil_runtime.record import RunRecord, RunResult
from hil_runtime.reference import ConditionTable, Reference
from hil_runtime.reporting import WARNING_COUNTERS, CounterRises, counters_dict, status_snapshot
from hil_runtime.sdnotify import Notifier
from hil_runtime.supervisor import Fault, FaultKind, Supervisor, classify_bus_error
from hil_runtime.telemetry.sink import NullTelemetry, TelemetrySink

log = logging.getLogger(__name__)


class StartupError(RuntimeError):
    """The daemon could not start (bus unreachable, drives silent): one line, exit 2, never enabled."""

    exit_code = 2


# --- the runtime ---------------------------------------------------------------------------------------


class Runtime:
    """One arm's runtime. Construct, configure, activate, run, shutdown (module docstring)."""

    def __init__(
        self,
        config: RuntimeConfig,
        bus: JointBus,
        *,
        bundle: PolicyBundle | None = None,
        telemetry: TelemetrySink | None = None,
        telemetry_for: Callable[[Runtime], TelemetrySink] | None = None,
        notifier: Notifier | None = None,
        record_cycles: int = 0,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.config = config
        self.bus = bus
        if bus.n_joints != len(config.bus.joints):
            raise RuntimeConfigError(
                f"{config.source}: bus: {bus.n_joints} drives on the bus, {len(config.bus.joints)} joints in the config"
            )
        self.bundle = bundle if bundle is not None else load_bundle_for(config)
        self.limits = safety_limits_for(config, self.bundle)
        self.condition = condition_for(config, self.limits)
        self.controller = Controller(
            self.bundle, config.bundle.mode, config.bundle.torque_rate_limit, config.bundle.velocity_filter_hz
        )
        self.supervisor = Supervisor(self.limits, config.joint_names)
        self.notifier = notifier if notifier is not None else Notifier(None)
        self.lifecycle = Lifecycle()
        self.lifecycle.subscribe(self._on_lifecycle)
        self._clock = clock
        self.pacer = Pacer(
            config.period_s,
            config.loop.pacing,
            clock=clock,
            sleep=sleep,
            stats_window=config.loop.stats_window,
            spin_s=config.loop_spin_s,
        )
        n = self.bundle.n_joints
        self.record = RunRecord(record_cycles, n)
        self._condition_table: ConditionTable | None = None  # built by configure, before any enable
        self.realtime = RealtimeReport()
        self.pipeline = CyclePipeline(
            self.supervisor, self.controller, self.record, config.joint_names, config.period_s, clock
        )
        # Wall time: a skipped period moves the reference on (a real arm moved meanwhile); cycles:
        # one reference row per exchange (a lock-stepped target advanced exactly one period).
        base = config.loop.time_base
        self.loop = ActiveLoop(
            self.pacer,
            bus,
            self.pipeline,
            self.notifier,
            wall_time=(config.loop.pacing == "clock") if base == "auto" else (base == "wall"),
            overlap=config.loop_overlaps,
            stats_interval_s=config.loop.stats_interval_s,
            publish_stats=self._publish_stats,
            stop_requested=lambda: self._stop,
        )
        self._stop = False
        self._reset = False
        self._reset_activates: bool | None = None  # None: loop.activate_on_reset decides
        self._activate = False
        self._wake = threading.Event()
        self._rt_thread: int | None = None
        self._ready_sent = False
        self._activations = 0
        self._faults = 0
        self.last_fault: Fault | None = None
        self.fault_cycle: int | None = None  # total_cycles when the last fault was entered
        self._last_stats: dict[str, Any] = {}
        self._rises = CounterRises()
        # Last: a sink built for this runtime (hil_runtime.factory: the Zenoh publisher names its stats
        # and takes its controls) needs the rest of it. Fixed for the runtime's life.
        sink = telemetry_for(self) if telemetry_for is not None else telemetry
        self._telemetry: TelemetrySink = sink if sink is not None else NullTelemetry()
        self.pipeline.telemetry = self._telemetry

    # --- requests from any thread -------------------------------------------------------------
    def request_stop(self) -> None:
        """Leave the loop at the next cycle boundary; drives quick-stopped and disabled (thread-safe)."""
        self._stop = True
        self._wake.set()

    def request_reset(self, activate: bool | None = None) -> None:
        """Clear FAULT (drive fault reset, then INACTIVE; ACTIVE again if loop.activate_on_reset).
        ``activate=False``: stay INACTIVE whatever the config says (a remote reset, docs/security.md)."""
        self._reset_activates = activate
        self._reset = True
        self._wake.set()

    def request_activate(self) -> None:
        """INACTIVE -> ACTIVE at the loop's next look (thread-safe)."""
        self._activate = True
        self._wake.set()

    @property
    def state(self) -> LifecycleState:
        return self.lifecycle.state

    @property
    def total_cycles(self) -> int:
        """Exchanges in ACTIVE (one that raised included: its frames went out)."""
        return self.pipeline.cycle

    @property
    def telemetry(self) -> TelemetrySink:
        """The sink given at construction (``telemetry`` or ``telemetry_for``; hil_runtime.factory)."""
        return self._telemetry

    @property
    def reference(self) -> Reference:
        return self.pipeline.reference

    # --- lifecycle transitions (the loop's thread) -----------------------------------------------
    def configure(self) -> None:
        """UNCONFIGURED -> INACTIVE: the bus connected (drives configured, no torque), the policy
        warm, telemetry started. A bus that does not come up raises :class:`StartupError`."""
        if not self.lifecycle.can(Transition.CONFIGURE):
            raise LifecycleError(f"cannot configure from {self.lifecycle.state.value}")
        try:
            self.bus.connect()
        except DriveError as exc:
            self._close_quietly()
            raise StartupError(f"{self.config.source}: bus: {exc}") from None
        except Exception as exc:  # noqa: BLE001 - python-can backends raise their own types
            self._close_quietly()
            raise StartupError(f"{self.config.source}: bus: {type(exc).__name__}: {exc}") from None
        self._warm_up()
        # The condition's rows now, before any enable: an hour at 1 kHz takes ~1.6 s to build,
        # longer than the drives may wait for their first set-point (comm-loss, heartbeats).
        if self.condition is not None:
            self._condition_table = ConditionTable.build(self.condition, self.config.period_s)
        self.telemetry.start()
        self.lifecycle.apply(Transition.CONFIGURE)

    def activate(self) -> bool:
        """INACTIVE -> ACTIVE: drives enabled, the reference ramped from the measured pose.
        False (and FAULT) when the drives refuse or the measured pose is already outside the limits."""
        self._activate = False
        if not self.lifecycle.can(Transition.ACTIVATE):  # never enable the drives from FAULT etc.
            raise LifecycleError(f"cannot activate from {self.lifecycle.state.value}")
        freeze_heap()  # before the drives run: a collection between two exchanges could stall them
        try:
            feedback = self.bus.enable(None)  # one period at zero torque; see docs/runtime.md
        except DriveError as exc:
            self._enter_fault(classify_bus_error(exc))
            return False
        except Exception as exc:  # nothing at run time may crash the loop thread
            log.exception("enable failed")
            self._enter_fault(Fault(FaultKind.INTERNAL, f"enable: {exc!r}"))
            return False
        q0 = np.array(feedback.position_rad, dtype=float)
        self.supervisor.stale_run = 0
        fault = self.supervisor.check_feedback(q0, feedback.velocity_rad_s, feedback.fresh)
        if fault is not None:
            self._enter_fault(fault)
            return False
        pipeline = self.pipeline
        pipeline.reference = self._build_reference(q0)
        # the rate limit (if any) starts from the set-point the drives hold now (enable's: zero)
        self.controller.reset(q0, feedback.commanded_torque_nm)
        self.loop.ref_base = 1
        pipeline.t0_s = now = self._clock()
        fault = pipeline.run(feedback, 0, now, now)
        if fault is not None:
            self._enter_fault(fault)
            return False
        self._activations += 1
        self.lifecycle.apply(Transition.ACTIVATE)
        self.telemetry.event(
            "activated", self.total_cycles, f"reference {self.reference.name}, ramp {self.reference.ramp_cycles} cycles"
        )
        log.info(
            "ACTIVE: reference %s, ramp %.3f s from %s",
            self.reference.name,
            self.reference.ramp_cycles * self.config.period_s,
            np.round(q0, 4).tolist(),
        )
        return True

    def shutdown(self) -> None:
        """Any state -> FINALIZED: drives quick-stopped (when they were enabled) and disabled, bus
        closed, telemetry closed. Never raises for the drives; idempotent."""
        if self.lifecycle.state is LifecycleState.FINALIZED:
            return
        if self.lifecycle.state is LifecycleState.ACTIVE or self.bus.enabled:
            self._quick_stop("shutdown")
        try:
            self.bus.disable()
        except DriveError as exc:
            log.warning("disable at shutdown: %s", exc)
        except Exception as exc:  # noqa: BLE001 - a bus that is already gone
            log.warning("disable at shutdown: %r", exc)
        self.notifier.stopping(f"FINALIZED after {self.total_cycles} cycles")
        self.lifecycle.apply(Transition.SHUTDOWN)
        self._close_quietly()
        try:
            self.telemetry.close()
        except Exception as exc:  # noqa: BLE001 - telemetry never keeps the daemon from stopping
            log.warning("telemetry close: %r", exc)

    # --- the loop -------------------------------------------------------------------------------
    def run(
        self, max_cycles: int | None = None, *, stop_on_fault: bool = False, shutdown_at_end: bool = False
    ) -> RunResult:
        """Run the lifecycle on the calling thread until a stop request, ``max_cycles`` ACTIVE
        cycles, ``loop.duration_s`` in ACTIVE, or (``stop_on_fault``) a fault. INACTIVE and FAULT
        wait for requests (activate, reset, stop) with the watchdog fed."""
        self._apply_thread_settings()
        reason = "stop"
        loop = self.config.loop
        duration_ticks = None if loop.duration_s is None else round(loop.duration_s / self.config.period_s)
        cycles_left = max_cycles
        try:
            while not self._stop:
                state = self.lifecycle.state
                if state is LifecycleState.ACTIVE:
                    reason = self._run_active(cycles_left, duration_ticks)
                    if cycles_left is not None:
                        cycles_left -= self.pacer.cycles
                    if reason in ("cycles", "duration"):
                        break
                    continue
                if state is LifecycleState.FAULT and stop_on_fault:
                    reason = "fault"
                    break
                if state is LifecycleState.INACTIVE and self._activate:
                    self.activate()
                    continue
                if state is LifecycleState.FAULT and self._reset:
                    self._do_reset()
                    continue
                if state in (LifecycleState.UNCONFIGURED, LifecycleState.FINALIZED):
                    raise RuntimeError(f"run() needs a configured runtime, it is {state.value}")
                self._idle()
            result = RunResult(
                reason if not self._stop else "stop",
                self.lifecycle.state,
                self.lifecycle.fault,
                self.total_cycles,
                self.stats(),
                self.fault_cycle,
            )
        finally:
            if shutdown_at_end:
                self.shutdown()
        return result

    def _idle(self) -> None:
        """INACTIVE/FAULT: wait for a request, keep the watchdog fed (the thread is alive)."""
        self._wake.wait(self.config.loop.idle_poll_s)
        self._wake.clear()
        self.notifier.watchdog_if_due(self._clock())

    def _run_active(self, max_cycles: int | None, duration_ticks: int | None) -> str:
        reason = self.loop.run(max_cycles, duration_ticks)
        if reason == "fault" and self.loop.fault is not None:
            self._enter_fault(self.loop.fault)
        self._publish_stats()
        return reason

    # --- faults, reset -------------------------------------------------------------------------------
    def _enter_fault(self, fault: Fault) -> None:
        """Quick-stop the drives (best effort), FAULT with the reason; the loop thread stays up."""
        self._quick_stop(fault.kind.value)
        # Only a reset (or activation) asked for after this fault may clear it: a stale request
        # from before would otherwise re-enable the drives without anyone having seen the fault.
        self._reset = False
        self._activate = False
        self.last_fault = fault
        self.fault_cycle = self.total_cycles
        self._faults += 1
        log.error("FAULT: %s", fault)
        self.lifecycle.apply(Transition.FAULT, str(fault))
        self.telemetry.event("fault", self.total_cycles, str(fault))

    def _quick_stop(self, why: str) -> None:
        try:
            self.bus.quick_stop()
        except Exception as exc:  # noqa: BLE001 - the stop must not raise past this point
            log.warning("quick stop (%s) failed: %r", why, exc)

    def _do_reset(self) -> None:
        self._reset = False
        try:
            self.bus.fault_reset()
        except DriveError as exc:
            self._enter_fault(classify_bus_error(exc))
            return
        except Exception as exc:  # noqa: BLE001 - any other failure of the reset is an internal FAULT
            self._enter_fault(Fault(FaultKind.INTERNAL, f"fault reset: {exc!r}"))
            return
        self.lifecycle.apply(Transition.RESET)
        self.telemetry.event("reset", self.total_cycles, "fault cleared")
        activate, self._reset_activates = self._reset_activates, None
        if self.config.loop.activate_on_reset and activate is not False:
            self.activate()

    # --- helpers -------------------------------------------------------------------------------------
    def _build_reference(self, q0: np.ndarray) -> Reference:
        ref = self.config.reference
        if self.condition is None:
            return Reference.hold(q0)
        if ref.start == "condition":  # the plant was placed on the condition's start (RunStart)
            return Reference.condition_only(self.condition, self.config.period_s, self._condition_table)
        return Reference.ramp_then(
            q0,
            self.condition,
            self.config.period_s,
            ref.ramp_s,
            self.limits.velocity_limit_rad_s,
            ref.ramp_speed_fraction,
            self._condition_table,
        )

    def _warm_up(self) -> None:
        """The cycle's pipeline before ACTIVE (onnxruntime's first calls allocate), nothing sent."""
        mid = 0.5 * (self.limits.position_lower_rad + self.limits.position_upper_rad)
        self.pipeline.warm_up(self.config.loop.warmup_cycles, mid)
        self.pacer.summary()  # its buffers touched once too

    def _apply_thread_settings(self) -> None:
        ident = threading.get_ident()
        if self._rt_thread == ident:
            return
        self._rt_thread = ident
        loop = self.config.loop
        # The helper threads (publisher, bus receive, Zenoh, onnxruntime) exist by now and keep
        # SCHED_OTHER; off the loop's CPU where the machine has another.
        if loop.cpu_affinity:
            keep_other_threads_off(loop.cpu_affinity, self.realtime)
            set_thread_affinity(loop.cpu_affinity, self.realtime)
        fifo = loop.fifo_priority is not None and set_thread_fifo(loop.fifo_priority, self.realtime)
        risk = clock_pacing_risk(self.config.period_s, fifo) if loop.pacing == "clock" else None
        if risk is not None:
            log.warning("real time: %s", risk)
            self.telemetry.event("warning", self.total_cycles, risk)

    def _close_quietly(self) -> None:
        try:
            self.bus.close()
        except Exception as exc:  # noqa: BLE001 - closing on the way out: report, never raise
            log.warning("closing the bus: %r", exc)

    def _on_lifecycle(self, state: LifecycleState, fault: str | None) -> None:
        self.telemetry.set_status(state.value, fault)
        if state is LifecycleState.ACTIVE and not self._ready_sent:
            self._ready_sent = True
            self.notifier.ready(self.status_line())
        else:
            self.notifier.status(self.status_line())

    def _publish_stats(self) -> None:
        stats = self.stats()
        self._last_stats = stats
        self.telemetry.offer_stats(stats)
        self.notifier.status(self.status_line(stats))
        # Anomalies the loop rides through (a late or malformed frame, an overrun, a substituted
        # torque) are counted where they happen and reported here, one event per stats interval.
        rose = self._rises.since_last(stats)
        if rose:
            self.telemetry.event("warning", self.total_cycles, rose)

    # --- reporting (any thread) ----------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """Numbers for telemetry ``stats`` (names of hil_runtime.telemetry.codec.STATS_FIELDS first)."""
        out: dict[str, Any] = dict(self.pacer.summary())
        counters = self.supervisor.counters()
        out["cycles"] = self.total_cycles
        out["fallbacks"] = counters.pop("fallback_cycles")
        out["saturations"] = counters.pop("saturated_cycles")
        out.update(counters)
        for name, value in counters_dict(self.bus.counters).items():
            out[f"bus_{name}"] = value
        out["activations"] = self._activations
        out["faults"] = self._faults
        out["record_overflow"] = self.record.overflow
        return out

    def status_line(self, stats: dict[str, Any] | None = None) -> str:
        state = self.lifecycle.state
        if state is LifecycleState.FAULT:
            return f"FAULT: {self.lifecycle.fault}"
        if state is LifecycleState.ACTIVE:
            stats = stats or self._last_stats
            rate = stats.get("rate_hz", math.nan) if stats else math.nan
            rate_text = "starting" if math.isnan(rate) else f"{rate:.0f} Hz"
            return (
                f"ACTIVE {rate_text}, {self.total_cycles} cycles, overruns {self.pacer.overruns}, "
                f"reference {self.reference.name}"
            )
        return str(state.value)

    def status(self) -> dict[str, Any]:
        """A JSON-able snapshot for the control socket (:func:`hil_runtime.reporting.status_snapshot`)."""
        return status_snapshot(self, self._last_stats or {})


__all__ = [
    "BundleError",
    "ConditionError",
    "RunRecord",
    "RunResult",
    "Runtime",
    "StartupError",
    "WARNING_COUNTERS",
    "condition_for",
    "load_bundle_for",
    "safety_limits_for",
]
