"""``hil demo``'s numbers: the runtime's record on the simulator's grid, the simulation twin, both
runs scored, the loop's timing from the runtime's own stats, and the telemetry the demo received
checked against the runtime's record. models/demo/report.py writes them out.

The simulation twin is the models simulator (RK4 plant, pinocchio) running the same bundle on the
same condition in this process, as ``hil experiment`` does; both runs are scored by
models.scoring, the composite normalized between the two (docs/scoring.md).
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from models.scoring import METRICS, composite_scores, run_metrics

if TYPE_CHECKING:
    from models.demo.session import HilOutcome


def hil_trajectory(
    record: dict[str, np.ndarray], steps: int, period_s: float
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The runtime's record on the simulator's grid t = k * period, k < steps.

    Lock-step: one row per period, taken as is. Real time: overrun periods were skipped (no row),
    so each column is interpolated onto the grid (the count is reported); a run cut short (a fault)
    is held at its last row, as hil experiment does."""
    t = np.asarray(record["t_s"], float)
    grid = np.arange(steps) * period_s
    info: dict[str, Any] = {"rows": int(t.size)}
    columns = ("q", "qd", "q_ref", "qd_ref", "tau", "tau_fb", "fallback", "compute_s", "exchange_s")
    inside = t < grid[-1] + 0.5 * period_s
    rows = int(inside.sum())
    uniform = rows >= 1 and np.allclose(t[:rows], grid[:rows], atol=1e-9)
    out: dict[str, np.ndarray] = {"t": grid}
    if uniform:
        for name in columns:
            value = np.asarray(record[name])[:rows]
            if rows < steps:
                value = np.concatenate([value, np.repeat(value[-1:], steps - rows, axis=0)])
            out[name] = value
        info["skipped_periods"] = 0
    else:
        info["skipped_periods"] = int(steps - rows)
        for name in columns:
            value = np.asarray(record[name], float)[:rows]
            if value.ndim == 1:
                out[name] = np.interp(grid, t[:rows], value)
            else:
                out[name] = np.stack([np.interp(grid, t[:rows], value[:, j]) for j in range(value.shape[1])], axis=1)
    info["covered_s"] = float(t[rows - 1] + period_s) if rows else 0.0
    info["complete"] = rows >= steps or (not uniform and info["covered_s"] >= grid[-1])
    return out, info


def simulate_twin(
    robot: Any, law: str, mode: str, condition: Any, gain_set: str, realism: Any = None
) -> tuple[dict[str, np.ndarray], float]:
    """The models simulator on the same bundle and condition; (trajectory, wall seconds)."""
    from models.feedback import make_law
    from models.modes import make_controller
    from models.sim import SimConfig, simulate

    sim = SimConfig()
    started = time.monotonic()
    controller = make_controller(mode, make_law(law, robot, sim.period_s, gain_set), robot)
    traj = simulate(robot, controller, [condition], sim, realism=realism)
    run = traj.run(0)
    run["within_limits"] = np.asarray(bool(traj.finite[0] and traj.within_limits[0]))
    return run, time.monotonic() - started


def compare(
    robot: Any, condition: Any, hil: dict[str, np.ndarray], sim: dict[str, np.ndarray], hil_fault: str | None
) -> dict[str, Any]:
    """The six metrics of both runs, the composite normalized between the two, and their difference."""
    dist = None if condition.disturbance is None else condition.disturbance.time_s
    m_hil = run_metrics(hil["t"], hil["q"], hil["q_ref"], dist)
    m_sim = run_metrics(sim["t"], sim["q"], sim["q_ref"], dist)
    hil_ok = bool(
        hil_fault is None
        and np.isfinite(hil["q"]).all()
        and float(np.max(robot.position_limit_ratio(hil["q"]))) <= 1.0
        and float(np.max(np.abs(hil["qd"]) / robot.velocity_limit_rad_s)) <= 1.0
    )
    sim_ok = bool(sim["within_limits"])
    failed = {(name, condition.name) for name, ok in (("hil", hil_ok), ("sim", sim_ok)) if not ok}
    composite = composite_scores({("hil", condition.name): m_hil, ("sim", condition.name): m_sim}, failed)
    diff_deg = np.degrees(hil["q"] - sim["q"])
    return {
        "metrics": {"hil": m_hil, "sim": m_sim},
        "relative": {
            m: (m_hil[m] - m_sim[m]) / abs(m_sim[m]) if m_sim[m] else (0.0 if m_hil[m] == 0 else math.inf)
            for m in METRICS
        },
        "composite": composite,
        "within_limits": {"hil": hil_ok, "sim": sim_ok},
        "trajectory_rms_diff_deg": float(np.sqrt(np.mean(diff_deg**2))),
        "trajectory_max_diff_deg": float(np.abs(diff_deg).max()),
        "fallback_cycles": {"hil": int((hil["fallback"] > 0).sum())},
    }


def timing_figures(stats: dict[str, float], record: dict[str, np.ndarray], period_s: float) -> dict[str, Any]:
    """The loop's figures from the runtime's own stats (its last telemetry ``stats``, which covers
    the whole run: the demo sets loop.stats_window above the run's length); the exchange (waiting
    on the bus) from its record."""

    def us(name: str) -> float | None:
        value = stats.get(name)
        return None if value is None or not math.isfinite(float(value)) else round(float(value) * 1e6, 1)

    exchange = np.asarray(record.get("exchange_s", np.zeros(0)), float)[1:] * 1e6
    figures: dict[str, Any] = {
        "period_target_us": period_s * 1e6,
        "rate_hz": None
        if not math.isfinite(float(stats.get("rate_hz", math.nan)))
        else round(float(stats["rate_hz"]), 1),
        "cycles": int(stats.get("cycles", 0) or 0),
        "overruns": int(stats.get("overruns", 0) or 0),
        "skipped_periods": int(stats.get("skipped_periods", 0) or 0)
        if math.isfinite(float(stats.get("skipped_periods", 0) or 0))
        else None,
        "period_us": {"median": us("period_median_s"), "p99": us("period_p99_s"), "max": us("period_max_s")},
        "compute_us": {"median": us("compute_median_s"), "p99": us("compute_p99_s"), "max": us("compute_max_s")},
        "exchange_us": (
            {
                "median": round(float(np.median(exchange)), 1),
                "p99": round(float(np.percentile(exchange, 99)), 1),
                "max": round(float(exchange.max()), 1),
            }
            if exchange.size
            else None
        ),
        "fallbacks": int(stats.get("fallbacks", 0) or 0),
        "saturations": int(stats.get("saturations", 0) or 0),
        "telemetry_sent": int(stats.get("telemetry_sent", 0) or 0),
        "telemetry_dropped": int(stats.get("telemetry_dropped", 0) or 0),
        "bus": {k[4:]: int(v) for k, v in stats.items() if k.startswith("bus_") and math.isfinite(float(v))},
    }
    return figures


def telemetry_recording(outcome: HilOutcome) -> Any:
    """The payloads the demo received, as ``hil telemetry record`` keeps them (decoded at the end)."""
    from hil_runtime.telemetry.codec import TelemetryDecodeError
    from hil_runtime.telemetry.subscriber import StateRecording

    recording = StateRecording(outcome.schema, payloads=list(outcome.state_payloads))
    for payloads, decode, target in (
        (outcome.status_payloads, outcome.schema.decode_status, recording.status),
        (outcome.event_payloads, outcome.schema.decode_event, recording.events),
    ):
        for payload in payloads:
            try:
                header, body = decode(payload)
            except TelemetryDecodeError:
                continue
            if not header.warmup:
                target.append({"seq": header.seq, "t_ns": header.t_ns, **body})
    return recording


def final_stats(outcome: HilOutcome) -> dict[str, float]:
    """The runtime's last ``stats`` sample (published as the loop left ACTIVE)."""
    from hil_runtime.telemetry.codec import TelemetryDecodeError

    for payload in reversed(outcome.stats_payloads):
        try:
            header, values = outcome.schema.decode_stats(payload)
        except TelemetryDecodeError:
            continue
        if not header.warmup:
            return {k: float(v) for k, v in values.items()}
    return {}


def telemetry_check(arrays: dict[str, np.ndarray], record: dict[str, np.ndarray]) -> dict[str, Any]:
    """What the subscriber received against the runtime's own record, cycle by cycle."""
    from hil_runtime.telemetry.subscriber import missing_samples

    seq = arrays["seq"].astype(np.int64)
    out: dict[str, Any] = {
        "samples": int(seq.size),
        "missing": missing_samples(arrays["seq"]),
        "gaps": int((arrays["flags"] & 1).astype(bool).sum()) if seq.size else 0,
    }
    if seq.size:
        # seq counts the runtime's offered states from 1; the record's row i is the i-th cycle.
        rows = seq - 1
        ok = (rows >= 0) & (rows < record["q"].shape[0])
        if ok.any():
            out["max_abs_q_diff_vs_record_rad"] = float(np.abs(arrays["q"][ok] - record["q"][rows[ok]]).max())
    return out


__all__ = [
    "compare",
    "final_stats",
    "hil_trajectory",
    "simulate_twin",
    "telemetry_check",
    "telemetry_recording",
    "timing_figures",
]
