"""One run of ``hil experiment --plant hil``: a fresh runtime loop on the target's bus for one
(law, mode, condition) (run by the lab, models/lab/runs.py), its record as the simulator's
trajectory, and the run's entry in results.json."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from models.conditions import Condition
from models.effort import effort_metrics
from models.hil_experiment.config import HilOptions, run_start
from models.lab.runs import CHUNK_CYCLES, is_rig_fault, placed_run_config, run_placed
from models.robots import RobotModel
from models.scoring import run_metrics

# A fault of the rig, not of the controller (models.lab.runs.RIG_FAULTS: the bus, the drives'
# state) runs the run again, up to RIG_RETRIES times; the retries are counted in results.json.
RIG_RETRIES = 2


@dataclass
class HilRun:
    """One run's record (the runtime's arrays, padded to the condition's length when it faulted)."""

    arrays: dict[str, np.ndarray]
    rows: int  # rows the runtime recorded (< steps when it faulted)
    fault: str | None
    stats: dict[str, Any]
    rig_retries: int = 0  # runs done again after a fault of the rig
    lateness: dict[str, Any] | None = None  # the free-running target's, over this run (sim_target/lateness.py)
    invalid_reason: str | None = None  # why the plant's lateness voids this run; None: valid
    rig_fault: bool = False  # the fault's kind (FaultKind, never its text) is one of the rig's


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
    A fault of the rig (the bus, not the controller) runs it again, RIG_RETRIES times."""
    from models.lmpc.controller import bundle_path

    data = placed_run_config(
        robot,
        bundle_path(robot.name, law, options.bundle_dir),
        mode,
        target.transport,
        period_s,
        conditions_file,
        condition,
        realtime_cpus=options.cpus if options.clock == "realtime" else None,
        torque_rate_limit=options.torque_rate_limit,
        velocity_filter_hz=options.velocity_filter_hz,
    )
    source = f"hil experiment {law}/{mode}/{condition.name}"
    retries = 0
    while True:
        run = _run_once(target, data, source, condition, period_s, advance)
        if not run.rig_fault or retries >= RIG_RETRIES:
            run.rig_retries = retries
            return run
        retries += 1


def _run_once(
    target: Any,
    data: dict[str, Any],
    source: str,
    condition: Condition,
    period_s: float,
    advance: Callable[[int], None] | None,
) -> HilRun:
    steps = int(round(condition.duration_s / period_s))
    placed = run_placed(target, data, source, run_start(condition), steps, advance)
    record = placed.record
    free_running = data["loop"]["pacing"] == "clock"
    lateness = None
    if free_running:
        record = resample_record(record, period_s, steps)  # wall slots: a skipped period holds the last row
        lateness = target.status().get("lateness")
    run = HilRun(pad_record(record, steps, period_s), int(record["q"].shape[0]), placed.fault, placed.stats)
    run.rig_fault = is_rig_fault(placed.fault_kind)
    if lateness is not None:
        from sim_target.lateness import invalid_reason

        run.lateness = lateness
        run.invalid_reason = invalid_reason(lateness, period_s)
    if advance is not None:  # a rig fault runs again: take its periods back; else count the rest as done
        shown = placed.periods_shown
        advance(-shown if run.rig_fault else steps - 1 - shown)
    return run


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
    "RIG_RETRIES",
    "HilRun",
    "pad_record",
    "resample_record",
    "run_on_target",
    "run_record",
]
