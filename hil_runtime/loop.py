"""The control loop, apart from the lifecycle: one cycle's pipeline and the ACTIVE loop around it.

:class:`CyclePipeline` is the one per-cycle pipeline. Activation (row 0, from the enable's
feedback), every ACTIVE cycle and the warm-up before ACTIVE all run it::

    supervisor.check_feedback ─▶ reference.at(k) ─▶ controller.step (one onnxruntime call)
        ─▶ supervisor.select_torque (the one clip, the one non-finite substitution) ─▶ controller.commit
        ─▶ the sample (CycleState) ─▶ telemetry.offer_state (one encoder) ─▶ record

:class:`ActiveLoop` paces it: ``pacer.wait`` ─▶ overrun budget ─▶ ``bus.exchange`` ─▶ pipeline
─▶ stats, watchdog. It never raises: a driver error (the driver has quick-stopped the drives), a
supervisor rule or a bug ends it with the :class:`~hil_runtime.supervisor.Fault` the lifecycle
enters (:class:`hil_runtime.runtime.Runtime` owns the lifecycle).

One name per quantity, each measured once on the loop's clock (the one the pacer uses):

- ``start_s``: the cycle's start (the pacer's); ``received_s``: when the exchange returned;
- ``exchange_s = received_s - start_s``: set-points out, feedback in;
- ``compute_s = ready_s - received_s``: feedback to set-points and sample ready (supervisor,
  reference, policy); the hand-off to telemetry and the record are not in it (the benchmark
  accounts for them apart, benchmarks/bench_runtime.py);
- the sample's ``t_ns``: ``received_s`` in nanoseconds (when the feedback it carries came in).

The overrun rule (docs/runtime.md, "Overruns"): the bundle's law runs at its declared fixed period
(its state integrates one period per cycle run); with clock pacing the reference follows the wall
clock (skipped periods move it on: the arm moved meanwhile); the drives hold the last set-point
through a late period (CiA 402). Late periods in a row (an overrun and the periods it skipped) are
counted against ``safety.overrun_budget``; past it: quick stop, FAULT ``overrun_budget``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from drivers.errors import DriveError
from drivers.joint_bus import JointBus
from hil_runtime.controller import Controller
from hil_runtime.pacer import Pacer
from hil_runtime.realtime import GcQuiet
from hil_runtime.record import RunRecord
from hil_runtime.reference import Reference
from hil_runtime.sdnotify import Notifier
from hil_runtime.supervisor import Fault, FaultKind, Supervisor, classify_bus_error
from hil_runtime.telemetry.sink import CycleState, NullTelemetry, TelemetrySink

log = logging.getLogger(__name__)


def bus_fault(exc: Exception, what: str) -> Fault:
    """The FAULT a failed bus call ends the loop with: a DriveError's kind (the driver has
    quick-stopped the drives already), anything else INTERNAL (``what``: which call)."""
    if isinstance(exc, DriveError):
        return classify_bus_error(exc)
    return Fault(FaultKind.INTERNAL, f"{what}: {exc!r}")


class CycleReadings(Protocol):
    """What the pipeline reads of a cycle's feedback (a JointFeedback has it)."""

    @property
    def position_rad(self) -> np.ndarray: ...

    @property
    def velocity_rad_s(self) -> np.ndarray: ...

    @property
    def fresh(self) -> np.ndarray: ...


@dataclass(slots=True)
class Readings:
    """Readings without a bus (warm-up)."""

    position_rad: np.ndarray
    velocity_rad_s: np.ndarray
    fresh: np.ndarray


class CyclePipeline:
    """Feedback -> set-points for one cycle (module docstring). ``command`` is the set-point buffer
    the next exchange sends; ``sample`` the one CycleState handed on (reused every cycle)."""

    def __init__(
        self,
        supervisor: Supervisor,
        controller: Controller,
        record: RunRecord,
        joint_names: tuple[str, ...],
        period_s: float,
        clock: Callable[[], float],
    ) -> None:
        n = controller.n_joints
        self.supervisor = supervisor
        self.controller = controller
        self.record = record
        self.telemetry: TelemetrySink = NullTelemetry()
        self.joint_names = joint_names
        self.period_s = period_s
        self.clock = clock
        self.reference: Reference = Reference.hold(np.zeros(n))
        self.command = np.zeros(n)
        self.sample = CycleState.zeros(n)
        self.t0_s = 0.0  # clock at activation: the record's wall_s origin
        self.cycle = 0  # the runtime's ACTIVE exchanges so far (events name it)

    def run(
        self, feedback: CycleReadings, k: int, start_s: float, received_s: float, publish: bool = True
    ) -> Fault | None:
        """Feedback -> supervisor -> reference row k -> policy -> supervisor -> :attr:`command`.

        None, or the FAULT to enter. ``publish=False`` (warm-up): nothing handed on or recorded.
        """
        q = feedback.position_rad
        qd = feedback.velocity_rad_s
        fresh = feedback.fresh
        supervisor = self.supervisor
        fault = supervisor.check_feedback(q, qd, fresh)
        if fault is not None:
            return fault
        if supervisor.stale_run == 1 and publish:  # the first stale cycle, said at once
            stale = [self.joint_names[i] for i in np.flatnonzero(~np.asarray(fresh, bool))]
            self.telemetry.event(
                "stale_feedback", self.cycle, f"no fresh feedback from {', '.join(stale)}; last values held"
            )
        q_d, qd_d, qdd_d = self.reference.at(k)
        controller = self.controller
        tau, tau_fb, fallback = controller.step(q, qd, q_d, qd_d, qdd_d)
        command = self.command
        fault = supervisor.select_torque(tau, tau_fb, fallback, command, controller.next_state)
        if fault is not None:
            return fault
        controller.commit(command)
        if not publish:
            return None
        compute_s = self.clock() - received_s
        sample = self.sample
        sample.seq += 1
        sample.t_ns = int(received_s * 1e9)
        sample.q = q
        sample.qd = qd
        sample.q_ref = q_d
        sample.qd_ref = qd_d
        sample.tau = command
        sample.tau_fb = tau_fb
        sample.fallback = fallback
        sample.compute_s = compute_s
        self.telemetry.offer_state(sample)
        record = self.record
        if record.capacity:
            record.add(sample, k * self.period_s, start_s - self.t0_s, received_s - start_s)
        return None

    def warm_up(self, cycles: int, mid_rad: np.ndarray) -> None:
        """Run the pipeline ``cycles`` times at ``mid_rad`` (onnxruntime's first calls allocate),
        nothing handed on; the reference, the controller and the counters are put back after."""
        n = mid_rad.shape[0]
        readings = Readings(mid_rad, np.zeros(n), np.ones(n, dtype=bool))
        reference = self.reference
        self.reference = Reference.hold(mid_rad)
        self.controller.reset(mid_rad)
        try:
            for k in range(cycles):
                self.run(readings, k, 0.0, 0.0, publish=False)
        finally:
            self.reference = reference
            self.supervisor.reset_counters()
            self.controller.reset(mid_rad)
            self.command[:] = 0.0


class ActiveLoop:
    """The ACTIVE loop on the calling thread (module docstring); :meth:`run` returns why it ended."""

    def __init__(
        self,
        pacer: Pacer,
        bus: JointBus,
        pipeline: CyclePipeline,
        notifier: Notifier,
        *,
        wall_time: bool,
        overlap: bool = False,
        stats_interval_s: float,
        publish_stats: Callable[[], None],
        stop_requested: Callable[[], bool],
    ) -> None:
        self.pacer = pacer
        self.bus = bus
        self.pipeline = pipeline
        self.notifier = notifier
        self.wall_time = wall_time  # reference index: period slots (skips included) or exchanges
        self.overlap = overlap  # bus.collect -> pipeline -> bus.send, not bus.exchange -> pipeline
        self.stats_interval_s = stats_interval_s
        self.publish_stats = publish_stats
        self.stop_requested = stop_requested
        self.ref_base = 1  # reference row of the pacer's tick 0: exchange k returns period k + 1
        self.fault: Fault | None = None  # why the last run() ended in "fault"

    def run(self, max_cycles: int | None, duration_ticks: int | None) -> str:
        """ "stop", "cycles", "duration" or "fault" (then :attr:`fault`)."""
        pacer = self.pacer
        bus = self.bus
        pipeline = self.pipeline
        compute = pipeline.run
        clock = pipeline.clock
        notifier = self.notifier
        exchange_stats = pacer.exchange_stats
        compute_stats = pacer.compute_stats
        sample = pipeline.sample
        stats_interval = self.stats_interval_s
        check_overruns = pipeline.supervisor.check_overruns
        command = pipeline.command
        base = self.ref_base
        wall_time = self.wall_time
        overlap = self.overlap
        # Overlapped cycles: the first cycle only sends the set-point computed before it (at
        # activation, or the last run's); each later cycle collects the feedback of the SYNC the
        # cycle before sent, computes, and sends. Its torque acts from this period, so its
        # reference row is the one a waiting cycle computes a period earlier: one row less.
        row_shift = 1 if overlap else 0
        sent = False  # overlap: a SYNC out whose feedback is not collected yet
        k = base - row_shift
        reason = "stop"
        self.fault = None
        with GcQuiet():
            pacer.start()
            next_stats = clock() + stats_interval
            while True:
                start = pacer.wait()
                if self.stop_requested():
                    break
                if pacer.late_run:  # this cycle started late: the budget rule (docs/runtime.md)
                    fault = check_overruns(pacer.late_run)
                    if fault is not None:
                        self.fault = fault
                        reason = "fault"
                        break
                pipeline.cycle += 1  # an exchange that raises still happened (frames went out)
                try:
                    if not overlap:
                        feedback = bus.exchange(command)
                    elif sent:
                        sent = False
                        feedback = bus.collect()
                    else:  # the first overlapped cycle: the set-point computed before this run
                        bus.send(command)
                        sent = True
                        continue
                except Exception as exc:  # noqa: BLE001 - nothing may crash the loop
                    self.fault = bus_fault(exc, "exchange")
                    reason = "fault"
                    break
                received = clock()
                try:
                    k = base - row_shift + (pacer.tick if wall_time else pacer.cycles - 1)
                    fault = compute(feedback, k, start, received)
                except Exception as exc:  # a bug must still stop the arm safely
                    log.exception("loop computation failed")
                    fault = Fault(FaultKind.INTERNAL, f"{type(exc).__name__}: {exc}")
                if fault is not None:
                    self.fault = fault
                    reason = "fault"
                    break
                exchange_s = received - start
                if overlap:
                    send_start = clock()
                    try:
                        bus.send(command)
                        sent = True
                    except Exception as exc:  # noqa: BLE001 - nothing may crash the loop
                        self.fault = bus_fault(exc, "send")
                        reason = "fault"
                        break
                    exchange_s += clock() - send_start  # collect + send: the bus's share of the cycle
                exchange_stats.add(exchange_s)
                compute_stats.add(sample.compute_s)
                done = clock()
                notifier.watchdog_if_due(done)
                if done >= next_stats:
                    next_stats = done + stats_interval
                    self.publish_stats()
                if max_cycles is not None and pacer.cycles >= max_cycles:
                    reason = "cycles"
                    break
                if duration_ticks is not None and k >= duration_ticks:
                    reason = "duration"
                    break
        if sent and reason != "fault":
            try:  # close the open SYNC: its feedback is not late at the next exchange
                bus.collect()
            except Exception as exc:  # noqa: BLE001 - the run ended; the next exchange reports it
                log.warning("closing the last overlapped cycle: %s", exc)
        if pacer.cycles:
            self.ref_base = k + 1  # a later run() goes on along the reference
        return reason
