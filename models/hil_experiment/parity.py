"""HIL against its simulated twin, run by run and per (law, mode): the score difference on one
scale (the simulation's) and the trajectory difference (docs/hil.md says why they differ)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

PARITY_TOLERANCE = 0.05  # the budget: HIL within 5 % of the simulation


def per_run_scores(
    runs: list[dict[str, Any]], scale: list[dict[str, Any]] | None = None
) -> dict[tuple[str, str, str], float]:
    """Composite score of each run (models.scoring's weights), normalized per condition and metric
    by the largest value among the runs of ``scale`` (default: ``runs`` themselves, as the table
    does) that stayed finite and inside the limits."""
    from models.scoring import METRICS, WEIGHTS

    scale = runs if scale is None else scale
    out: dict[tuple[str, str, str], float] = {}
    for cond in sorted({r["condition"] for r in runs}):
        reference = [r for r in scale if r["condition"] == cond]
        healthy = [r for r in reference if r["finite"] and r["within_limits"]] or reference
        largest = {m: max(r["metrics"][m] for r in healthy) for m in METRICS}
        for r in runs:
            if r["condition"] == cond:
                normalized = [r["metrics"][m] / largest[m] if largest[m] > 0 else 0.0 for m in METRICS]
                out[(r["law"], r["mode"], cond)] = sum(w * x for w, x in zip(WEIGHTS, normalized, strict=True))
    return out


def _relative(a: float, b: float) -> float:
    return (a - b) / abs(b) if b else (0.0 if a == b else math.inf)


def parity(
    hil: dict[str, Any],
    sim: dict[str, Any],
    trajectories: dict[tuple[str, str, str], dict[str, np.ndarray]],
    sim_traj_dir: Path,
) -> dict[str, Any]:
    """HIL vs simulation, per run and per (law, mode): score difference, trajectory RMS difference."""
    # One scale for both: the simulation's table. Each table's own normalization couples every law
    # to the worst run of its condition (one law that differs would move every other law's score).
    sim_scores = per_run_scores(sim["runs"])
    hil_scores = per_run_scores(hil["runs"], scale=sim["runs"])
    sim_runs = {(r["law"], r["mode"], r["condition"]): r for r in sim["runs"]}
    per_run = []
    for r in hil["runs"]:
        key = (r["law"], r["mode"], r["condition"])
        twin = sim_runs[key]
        s = np.load(sim_traj_dir / f"{key[0]}_{key[1]}_{key[2]}.npz")
        h = trajectories[key]
        diff_deg = np.degrees(h["q"] - s["q"])
        rms_diff = float(np.sqrt(np.mean(diff_deg**2)))
        sim_rmse = twin["metrics"]["rmse"]
        # The first sample whose difference exceeds 1e-3 deg: where the two plants part.
        apart = np.flatnonzero(np.abs(diff_deg).max(axis=1) > 1e-3)
        per_run.append(
            {
                "law": key[0],
                "mode": key[1],
                "condition": key[2],
                "score_hil": hil_scores[key],
                "score_sim": sim_scores[key],
                "score_rel": _relative(hil_scores[key], sim_scores[key]),
                "trajectory_rms_diff_deg": rms_diff,
                "trajectory_rms_diff_per_joint_deg": np.sqrt(np.mean(diff_deg**2, axis=0)).tolist(),
                "trajectory_max_diff_deg": float(np.abs(diff_deg).max()),
                "trajectory_rms_diff_rel_to_sim_rmse": rms_diff / sim_rmse if sim_rmse > 0 else math.inf,
                "torque_rms_diff_nm": np.sqrt(np.mean((h["tau"] - s["tau"]) ** 2, axis=0)).tolist(),
                "first_apart_1e-3_deg_s": float(h["t"][apart[0]]) if apart.size else None,
                "metrics_rel": {m: _relative(r["metrics"][m], twin["metrics"][m]) for m in r["metrics"]},
                "both_within_limits": bool(r["within_limits"] and twin["within_limits"]),
            }
        )
    table: dict[str, dict[str, Any]] = {}
    for law, row in hil["table"].items():
        table[law] = {}
        for mode in row:
            mine = [p for p in per_run if p["law"] == law and p["mode"] == mode]
            # A run that faulted or left the limits in either plant is not compared: its score is that
            # of a partial or failed run (reported as such), never averaged into the parity figure.
            compared = [p for p in mine if p["both_within_limits"]]
            h_score = float(np.mean([p["score_hil"] for p in compared])) if compared else None
            s_score = float(np.mean([p["score_sim"] for p in compared])) if compared else None
            rel = _relative(h_score, s_score) if h_score is not None and s_score is not None else None
            table[law][mode] = {
                "score_hil": h_score,
                "score_sim": s_score,
                "score_rel": rel,
                "runs_compared": len(compared),
                "runs_failed": len(mine) - len(compared),
                "score_hil_own_table": row[mode]["score"],
                "score_sim_own_table": sim["table"][law][mode]["score"],
                "trajectory_rms_diff_deg": float(np.sqrt(np.mean([p["trajectory_rms_diff_deg"] ** 2 for p in mine]))),
                "trajectory_rms_diff_rel_to_sim_rmse": max(p["trajectory_rms_diff_rel_to_sim_rmse"] for p in mine),
                "within_tolerance": rel is not None and abs(rel) <= PARITY_TOLERANCE,
            }
    return {
        "tolerance": PARITY_TOLERANCE,
        "table": table,
        "runs": per_run,
        "sim_config": sim["config"],
        "sim_all_runs_within_limits": sim["all_runs_finite_and_within_limits"],
    }


__all__ = ["PARITY_TOLERANCE", "parity", "per_run_scores"]
