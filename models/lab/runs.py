"""One HIL run of the experiment (``hil experiment --plant hil``) on a launched target: a fresh
runtime (:func:`hil_runtime.factory.build_runtime`) on the target's bus, the arm placed on the
condition, the loop for the condition's duration or until a fault, the drives stopped; what it
recorded, and the fault's :class:`~hil_runtime.supervisor.FaultKind` (never parsed from its text).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil_runtime.supervisor import FaultKind
from models.lab import configs as lab

# Faults of the rig, not of the controller (a lock-stepped run's result cannot depend on them):
# the experiment runs such a run again (models/hil_experiment/target_runs.py, RIG_RETRIES).
RIG_FAULTS = frozenset(
    {
        FaultKind.FEEDBACK_TIMEOUT,
        FaultKind.HEARTBEAT_LOST,
        FaultKind.TRANSPORT,
        FaultKind.DRIVE_STATE,
        FaultKind.STALE_FEEDBACK,
    }
)
CHUNK_CYCLES = 250  # the lock-stepped loop runs in chunks of this many cycles so the progress bar moves
# Bounds on waits for frames, not assertions on time: a lock-stepped target does not care about
# wall time, and on a shared 2-core machine a niced experiment was measured stalled for over 1 s
# (a feedback timeout of 50 ms and a heartbeat timeout of 1 s then faulted runs that were fine).
# The drives' own master-loss watch (comm_loss_timeout_s) stays on: a dead experiment process
# still leaves the arm quick-stopped, after 10 s. ``hil demo`` runs with the same.
DRIVER_TIMEOUTS: Mapping[str, float] = {
    "feedback_timeout_s": 1.0,  # the driver config's upper bound (drivers/config.py, issue 20)
    "heartbeat_timeout_s": 10.0,
    "sdo_timeout_s": 5.0,
    "state_change_timeout_s": 10.0,
    "comm_loss_timeout_s": 10.0,
}


def is_rig_fault(kind: FaultKind | None) -> bool:
    """A fault of the rig (the bus, the drives' state), not of the controller (RIG_FAULTS)."""
    return kind in RIG_FAULTS


@dataclass
class PlacedRun:
    """What the runtime recorded over one placed run."""

    record: dict[str, np.ndarray]  # the runtime's record arrays (t_s, q, qd, ...), one row per exchange
    fault: str | None  # the lifecycle's fault ("kind: detail"), None when the run was clean
    fault_kind: FaultKind | None  # Runtime.last_fault's kind
    stats: dict[str, Any]
    periods_shown: int  # periods already reported to the progress callback


def placed_run_config(
    robot: Any,
    bundle: Path,
    mode: str,
    transport: Mapping[str, Any],
    period_s: float,
    conditions_file: Path,
    condition: Any,
    realtime_cpus: str | None = None,
    torque_rate_limit: str = "none",
    velocity_filter_hz: float | None = None,
) -> dict[str, Any]:
    """The runtime's config for one placed run: lock-step (bus pacing, no ramp: the arm is placed),
    or free-running on the wall clock for the condition's duration (``realtime_cpus``);
    ``torque_rate_limit``: the bundle's output limit (none | libfranka); ``velocity_filter_hz``: its
    velocity input filter (None: off)."""
    loop = (
        lab.realtime_loop(condition.duration_s, realtime_cpus, int(round(condition.duration_s / period_s)) + 1000)
        if realtime_cpus is not None
        else None
    )
    return lab.runtime_config(
        robot.name,
        lab.robot_joints(robot.joint_names, robot.torque_limit_nm),
        bundle,
        mode,
        transport,
        period_s,
        driver=DRIVER_TIMEOUTS,
        reference=lab.condition_reference(conditions_file, condition.name),
        loop=loop,
        torque_rate_limit=torque_rate_limit,
        velocity_filter_hz=velocity_filter_hz,
    )


def run_placed(
    target: Any,
    config_data: Mapping[str, Any],
    source: str,
    start: Mapping[str, Any],
    steps: int,
    advance: Callable[[int], None] | None = None,
) -> PlacedRun:
    """One run of ``config_data`` on ``target`` (a :class:`sim_target.launch.LaunchedTarget`): the
    runtime configured, the target's run ``start`` (placement, disturbance) armed, activated, run
    for ``steps`` rows (lock-step, in chunks) or ``loop.duration_s`` (free-running), shut down."""
    from hil_runtime.config import parse_runtime_config
    from hil_runtime.factory import build_runtime
    from sim_target.config import parse_run_start

    config = parse_runtime_config(dict(config_data), source)
    runtime = build_runtime(config, telemetry=False, record_cycles=steps)
    shown = 0  # periods shown on the progress bar for this run
    try:
        runtime.configure()
        target.start_run(parse_run_start(dict(start), "start"))
        active = runtime.activate()
        if active and config.loop.pacing == "clock":  # free-running: no chunks, no pause between them
            runtime.run(stop_on_fault=True)  # until loop.duration_s of wall time in ACTIVE, or a fault
        elif active:
            done = 0
            while done < steps - 1:  # row 0 is the activation's feedback (t = 0)
                result = runtime.run(max_cycles=min(CHUNK_CYCLES, steps - 1 - done), stop_on_fault=True)
                done = runtime.record.n - 1
                if advance is not None:
                    advance(done - shown)
                    shown = done
                if result.reason == "fault":
                    break
        fault = runtime.lifecycle.fault
        kind = runtime.last_fault.kind if fault is not None and runtime.last_fault is not None else None
        stats = runtime.stats()
    finally:
        runtime.shutdown()
        if config.loop.pacing == "clock":
            _release_thread_settings()
    record = {k: np.array(v) for k, v in runtime.record.arrays().items()}
    return PlacedRun(record, fault, kind, stats, shown)


def _release_thread_settings() -> None:
    """The loop ran on this thread with SCHED_FIFO on one CPU: back to the default policy and every
    CPU, so the next run's bus threads (created before its loop starts) do not inherit them."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setaffinity(0, range(os.cpu_count() or 1))


__all__ = [
    "CHUNK_CYCLES",
    "DRIVER_TIMEOUTS",
    "RIG_FAULTS",
    "PlacedRun",
    "is_rig_fault",
    "placed_run_config",
    "run_placed",
]
