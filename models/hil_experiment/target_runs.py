"""One run of ``hil experiment --plant hil``: a fresh runtime loop on the target's bus for one
(law, mode, condition), its record as the simulator's trajectory, and the run's entry in
results.json."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from models.conditions import Condition
from models.effort import effort_metrics
from models.hil_experiment.config import HilOptions, run_start, runtime_config_dict
from models.robots import RobotModel
from models.scoring import run_metrics

if TYPE_CHECKING:
    from hil_runtime.config import RuntimeConfig

# Faults of the rig, not of the controller (a lock-stepped run's result cannot depend on them):
# such a run is run again, up to RIG_RETRIES times, and the retries are counted in results.json.
RIG_FAULTS = ("feedback_timeout", "heartbeat_lost", "transport", "drive_state", "stale_feedback")
RIG_RETRIES = 2
CHUNK_CYCLES = 250  # the loop runs in chunks of this many cycles so the progress bar moves


@dataclass
class HilRun:
    """One run's record (the runtime's arrays, padded to the condition's length when it faulted)."""

    arrays: dict[str, np.ndarray]
    rows: int  # rows the runtime recorded (< steps when it faulted)
    fault: str | None
    stats: dict[str, Any]
    rig_retries: int = 0  # runs done again after a fault of the rig (RIG_FAULTS)
    lateness: dict[str, Any] | None = None  # the free-running target's, over this run (sim_target/lateness.py)
    invalid_reason: str | None = None  # why the plant's lateness voids this run; None: valid

    @property
    def rig_fault(self) -> bool:
        return self.fault is not None and self.fault.split(":", 1)[0] in RIG_FAULTS


def run_on_target(
    target: Any,
    robot: RobotModel,
    law: str,
    mode: str,
    condition: Condition,
    period_s: float,
    options: HilOptions,
    conditions_file: Path,
    advance: Callable[[int], None] | None = None,
) -> HilRun:
    """One run: a fresh runtime on the target's bus, the arm placed on the condition, the loop for
    the condition's duration (or until a fault), the drives stopped. ``target``: a LaunchedTarget.
    A fault of the rig (RIG_FAULTS: the bus, not the controller) runs it again, RIG_RETRIES times."""
    from hil_runtime.config import parse_runtime_config
    from models.lmpc.controller import bundle_path

    data = runtime_config_dict(
        robot,
        bundle_path(robot.name, law, options.bundle_dir),
        mode,
        target.transport,
        period_s,
        conditions_file,
        condition.name,
    )
    if options.clock == "realtime":  # free-running: wall-clock deadlines, the loop on its own CPU
        from sim_target.rt_settings import split_cpus

        data["loop"] = {
            "pacing": "clock",
            "time_base": "wall",
            "duration_s": condition.duration_s,
            "stats_interval_s": 3600.0,
            "stats_window": min(int(round(condition.duration_s / period_s)) + 1000, 1 << 20),
            "cpu_affinity": split_cpus(options.cpus)[0],
            "fifo_priority": 80,
        }
    config = parse_runtime_config(data, f"hil experiment {law}/{mode}/{condition.name}")
    retries = 0
    while True:
        run = _run_once(target, config, condition, period_s, advance)
        if not run.rig_fault or retries >= RIG_RETRIES:
            run.rig_retries = retries
            return run
        retries += 1


def _run_once(
    target: Any,
    config: RuntimeConfig,
    condition: Condition,
    period_s: float,
    advance: Callable[[int], None] | None,
) -> HilRun:
    from drivers.drive_bus import DriveBus
    from hil_runtime.runtime import Runtime
    from sim_target.config import parse_run_start

    steps = int(round(condition.duration_s / period_s))
    runtime = Runtime(config, DriveBus(config.bus), record_cycles=steps)
    fault: str | None = None
    shown = 0  # periods shown on the progress bar for this run
    try:
        runtime.configure()
        target.start_run(parse_run_start(run_start(condition), "start"))
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
        stats = runtime.stats()
    finally:
        runtime.shutdown()
        if config.loop.pacing == "clock":
            _release_thread_settings()
    record = {k: np.array(v) for k, v in runtime.record.arrays().items()}
    lateness = None
    if config.loop.pacing == "clock":
        record = resample_record(record, period_s, steps)  # wall slots: a skipped period holds the last row
        lateness = target.status().get("lateness")
    run = HilRun(pad_record(record, steps, period_s), int(record["q"].shape[0]), fault, stats)
    if lateness is not None:
        from sim_target.lateness import invalid_reason

        run.lateness = lateness
        run.invalid_reason = invalid_reason(lateness, period_s)
    if advance is not None:  # a rig fault runs again: take its periods back; else count the rest as done
        advance(-shown if run.rig_fault else steps - 1 - shown)
    return run


def _release_thread_settings() -> None:
    """The loop ran on this thread with SCHED_FIFO on one CPU: back to the default policy and every
    CPU, so the next run's bus threads (created before its loop starts) do not inherit them."""
    import contextlib
    import os

    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setaffinity(0, range(os.cpu_count() or 1))


def resample_record(
    record: dict[str, np.ndarray], period_s: float, max_rows: int | None = None
) -> dict[str, np.ndarray]:
    """A free-running record (one row per exchange, ``t_s`` on wall-clock period slots, a skipped
    slot missing) as one row per period, at most ``max_rows``: a missing slot repeats the row before
    it (the drives held that torque, the arm was last seen there)."""
    rows = record["q"].shape[0]
    if rows == 0:
        return record
    slots = np.rint(record["t_s"] / period_s).astype(int)
    slots -= slots[0]
    count = slots[-1] + 1 if max_rows is None else min(slots[-1] + 1, max_rows)
    index = np.searchsorted(slots, np.arange(count), side="right") - 1
    out = {key: value[index] for key, value in record.items()}
    out["t_s"] = np.arange(count) * period_s
    return out


def pad_record(record: dict[str, np.ndarray], steps: int, period_s: float) -> dict[str, np.ndarray]:
    """The record as the simulator's trajectory (t, q, qd, ...), ``steps`` rows; a run cut short by a
    fault is held at its last position (the brakes hold it), like a diverged simulated run."""
    rows = record["q"].shape[0]
    out = {"t": np.arange(steps) * period_s}
    for key, value in record.items():
        if key == "t_s":
            continue
        if rows == 0:
            out[key] = np.full((steps, *value.shape[1:]), np.nan)
            continue
        if rows < steps:
            fill = np.repeat(value[-1:], steps - rows, axis=0)
            if key in ("qd", "tau", "tau_fb", "qd_ref"):
                fill = np.zeros_like(fill)
            value = np.concatenate([value, fill])
        out[key] = value[:steps]
    if rows:
        np.testing.assert_allclose(record["t_s"], out["t"][:rows], atol=1e-9)  # lock-step: one row per period
    return out


def run_record(robot: RobotModel, law: str, mode: str, condition: Condition, run: HilRun, steps: int) -> dict[str, Any]:
    a = run.arrays
    dist_time = None if condition.disturbance is None else condition.disturbance.time_s
    finite = bool(np.isfinite(a["q"]).all() and np.isfinite(a["qd"]).all())
    position_ratio = float(np.max(robot.position_limit_ratio(a["q"]))) if finite else math.inf
    velocity_ratio = float(np.max(np.abs(a["qd"]) / robot.velocity_limit_rad_s)) if finite else math.inf
    stats = run.stats
    compute_us = a["compute_s"][1 : run.rows] * 1e6 if run.rows > 1 else np.zeros(1)
    valid = run.invalid_reason is None
    return {
        "law": law,
        "mode": mode,
        "condition": condition.name,
        "metrics": run_metrics(a["t"], a["q"], a["q_ref"], dist_time),
        "finite": finite,
        # An INVALID run (its free-running plant fell behind the wall clock) is kept out of the
        # scores like a failed one: its figures are not a test of the controller.
        "within_limits": valid and finite and run.fault is None and position_ratio <= 1.0 and velocity_ratio <= 1.0,
        "valid": valid,
        "invalid_reason": run.invalid_reason,
        "position_limit_ratio": position_ratio,
        "velocity_limit_ratio": velocity_ratio,
        "max_abs_torque_nm": np.abs(a["tau"]).max(axis=0).tolist(),
        "effort": effort_metrics(a["tau"], a["qd"], robot.torque_limit_nm, float(a["t"][1] - a["t"][0]), run.rows),
        "hil": {
            "rows": run.rows,
            "steps": steps,
            "fault": run.fault,
            "rig_retries": run.rig_retries,
            "compute_us": {
                "median": float(np.median(compute_us)),
                "p99": float(np.percentile(compute_us, 99)),
                "max": float(compute_us.max()),
            },
            "fallback_cycles": int((a["fallback"][: run.rows] > 0).sum()),
            "saturations": int(stats.get("saturations", 0)),
            "bus": {k[4:]: v for k, v in stats.items() if k.startswith("bus_")},
            "plant_lateness": run.lateness,
        },
    }


__all__ = [
    "CHUNK_CYCLES",
    "RIG_FAULTS",
    "RIG_RETRIES",
    "HilRun",
    "pad_record",
    "resample_record",
    "run_on_target",
    "run_record",
]
