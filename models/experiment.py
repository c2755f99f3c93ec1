"""The paper's simulation experiment: laws x modes x conditions -> Table I, trajectories, plots.

Outputs in ``out_dir``:
  results.json   raw metrics per run, composite scores, eta, controller time per cycle, limits
  table.md       the layout of the paper's Table I
  trajectories/  one .npz per run (t, q, qd, q_ref, qd_ref, tau[, tau_fb])
  plots/         per-joint tracking error per law and condition (like the paper's Fig. 5)
"""

from __future__ import annotations

import json
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from hil_runtime.machine import machine
from hil_runtime.outputs import atomic_path, write_text_atomic
from models.conditions import Condition, Mismatch
from models.effort import deployable, effort_composite, effort_metrics, format_effort_table
from models.feedback import DEFAULT_GAIN_SET, LAW_NAMES, LAW_TITLES, make_law
from models.modes import make_controller
from models.robots import RobotModel
from models.scoring import METRICS, composite_scores, improvement, run_metrics
from models.sim import ControllerStack, SimConfig, Trajectory, batch_key, simulate
from sim_target.realism import RealismSpec

#: Plant-model mismatch of issue 3: +0.5 kg on the flange, link inertias alternately +/-20 %.
PAPER_MISMATCH = Mismatch(payload_kg=0.5, inertia_scale=(1.2, 0.8, 1.2, 0.8, 1.2, 0.8))


@dataclass(frozen=True)
class ExperimentConfig:
    laws: tuple[str, ...] = LAW_NAMES
    modes: tuple[str, ...] = ("fb",)
    gain_set: str = DEFAULT_GAIN_SET  # "stabilized" or "paper" (models.feedback.GAIN_SETS)
    sim: SimConfig = SimConfig()
    timing_cycles: int = 1000  # single-robot cycles timed per (law, mode) for the t columns
    save_trajectories: bool = True
    plots: bool = True
    realism: str = "ideal"  # a profile name (ideal, realistic, harsh) or a profile file (docs/realism.md)


def realism_spec(config: ExperimentConfig, robot: RobotModel) -> RealismSpec:
    """The experiment's realism profile bound to the robot and the simulator's physics step."""
    from sim_target.realism_profiles import load_realism

    return load_realism(
        config.realism,
        robot.n_joints,
        config.sim.period_s,
        config.sim.period_s / config.sim.substeps,
        robot.torque_limit_nm,
    )


def _groups(conditions: list[Condition]) -> list[list[int]]:
    """Indices of conditions that can share one vectorized plant (same duration, disturbance, mismatch)."""
    groups: dict[tuple, list[int]] = defaultdict(list)
    for i, c in enumerate(conditions):
        groups[batch_key(c)].append(i)
    return list(groups.values())


def time_controller(
    mode: str,
    law_name: str,
    robot: RobotModel,
    condition: Condition,
    sim: SimConfig,
    cycles: int,
    options: dict[str, Any],
    gain_set: str = DEFAULT_GAIN_SET,
) -> dict[str, float]:
    """Per-cycle wall time (ms) of one controller on a single robot, closed loop, over ``cycles`` periods."""
    controller = make_controller(mode, make_law(law_name, robot, sim.period_s, gain_set), robot, **options)
    short = replace(condition, duration_s=min(condition.duration_s, cycles * sim.period_s))
    simulate(robot, controller, [short], sim)
    samples = np.asarray(controller.cycle_times_s[10:] or controller.cycle_times_s) * 1e3
    return {
        "median_ms": float(np.median(samples)),
        "p99_ms": float(np.percentile(samples, 99)),
        "cycles": int(samples.size),
    }


def run_experiment(
    robot: RobotModel,
    conditions: list[Condition],
    config: ExperimentConfig,
    out_dir: Path,
    controller_options: dict[str, dict[str, Any]] | None = None,
    progress: Callable[[str, int], Callable[[int], None]] | None = None,
) -> dict[str, Any]:
    """Run every (law, mode) on every condition; write the outputs; return the results dict.

    ``progress(label, total_periods)`` returns a callable advancing a progress bar.
    """
    world = realism_spec(config, robot)  # a bad profile fails here, before any work
    out_dir.mkdir(parents=True, exist_ok=True)
    options = controller_options or {}
    runs: list[dict[str, Any]] = []
    trajectories: dict[tuple[str, str, str], dict[str, np.ndarray]] = {}
    timing: dict[str, dict[str, dict[str, float]]] = defaultdict(dict)
    steps = {c.name: int(round(c.duration_s / config.sim.period_s)) for c in conditions}
    # Every input before any work: the LMPC bundles (present, intact, of these laws) load now, not
    # after the FB and HMPC runs (minutes) have been computed and thrown away with the error.
    if "lmpc" in config.modes:
        for law in config.laws:
            make_controller(
                "lmpc", make_law(law, robot, config.sim.period_s, config.gain_set), robot, **options.get("lmpc", {})
            )

    for mode in config.modes:
        for group in _groups(conditions):
            group_conditions = [conditions[i] for i in group]
            # Every law runs side by side in one vectorized plant; HMPC-type modes likewise.
            controllers = [
                make_controller(
                    mode, make_law(law, robot, config.sim.period_s, config.gain_set), robot, **options.get(mode, {})
                )
                for law in config.laws
            ]
            stack = ControllerStack(controllers, [len(group_conditions)] * len(controllers))
            batch = [c for _ in config.laws for c in group_conditions]
            total = steps[group_conditions[0].name]
            advance = (
                progress(f"{mode}: {len(config.laws)} laws x {len(group)} conditions", total) if progress else None
            )
            traj = simulate(robot, stack, batch, config.sim, progress=advance, realism=world)
            for b, (law, condition) in enumerate((law, c) for law in config.laws for c in group_conditions):
                runs.append(_run_record(law, mode, condition, traj, b, robot, config.sim.period_s))
                trajectories[(law, mode, condition.name)] = traj.run(b)
        for law in config.laws:
            timing[law][mode] = time_controller(
                mode,
                law,
                robot,
                conditions[0],
                config.sim,
                config.timing_cycles,
                options.get(mode, {}),
                config.gain_set,
            )

    results = summarize(runs, timing, config, robot, conditions)
    results["controller_options"] = {m: {k: str(v) for k, v in o.items()} for m, o in options.items()}
    write_outputs(out_dir, config, conditions, trajectories, format_table(results), results)
    return results


def write_outputs(
    out_dir: Path,
    config: ExperimentConfig,
    conditions: list[Condition],
    trajectories: dict[tuple[str, str, str], dict[str, np.ndarray]],
    table: str,
    results: dict[str, Any],
    more_plots: Callable[[Path], None] | None = None,
) -> None:
    """An experiment's files (simulation or HIL): trajectories, plots (``more_plots(plots_dir)`` adds
    its own), table.md, results.json. Every file complete or absent (temporary name, then rename:
    Ctrl-C or a full disk leaves no half file), and results.json last: its presence means the run's
    outputs are all there."""
    if config.save_trajectories:
        traj_dir = out_dir / "trajectories"
        traj_dir.mkdir(exist_ok=True)
        for (law, mode, cond), arrays in trajectories.items():
            with atomic_path(traj_dir / f"{law}_{mode}_{cond}.npz") as tmp:
                np.savez_compressed(tmp, **arrays)
    if config.plots:
        from models.plots import plot_tracking_errors

        plot_tracking_errors(trajectories, config.laws, config.modes, [c.name for c in conditions], out_dir / "plots")
        if more_plots is not None:
            more_plots(out_dir / "plots")
    write_text_atomic(out_dir / "table.md", table)
    write_text_atomic(out_dir / "results.json", json.dumps(results, indent=2))


def _run_record(
    law: str, mode: str, condition: Condition, traj: Trajectory, b: int, robot: RobotModel, period_s: float
) -> dict[str, Any]:
    dist_time = None if traj.disturbance is None else traj.disturbance.time_s
    return {
        "law": law,
        "mode": mode,
        "condition": condition.name,
        "metrics": run_metrics(traj.t_s, traj.q[b], traj.q_ref[b], dist_time),
        "finite": bool(traj.finite[b]),
        "within_limits": bool(traj.within_limits[b]),
        "position_limit_ratio": float(traj.position_ratio[b]),
        "velocity_limit_ratio": float(traj.velocity_ratio[b]),
        "max_abs_torque_nm": np.abs(traj.tau[b]).max(axis=0).tolist(),
        "effort": effort_metrics(traj.tau[b], traj.qd[b], robot.torque_limit_nm, period_s),
    }


def verdicts(runs: list[dict[str, Any]], robot: RobotModel, period_s: float) -> None:
    """Each run's deployable verdict (docs/scoring.md), against the feedback law's run on the same
    condition when the table has one; stored in the run record as ``verdict``."""
    fb = {(r["law"], r["condition"]): r for r in runs if r["mode"] == "fb"}
    for r in runs:
        r["verdict"] = deployable(
            r, fb.get((r["law"], r["condition"])), robot.torque_limit_nm, period_s, robot.torque_rate_nm_s
        )


def summarize(
    runs: list[dict[str, Any]], timing: dict, config: ExperimentConfig, robot: RobotModel, conditions: list[Condition]
) -> dict[str, Any]:
    metrics = {(f"{r['law']}/{r['mode']}", r["condition"]): r["metrics"] for r in runs}
    failed = {(f"{r['law']}/{r['mode']}", r["condition"]) for r in runs if not (r["finite"] and r["within_limits"])}
    scores = composite_scores(metrics, failed)
    verdicts(runs, robot, config.sim.period_s)
    effort = {(f"{r['law']}/{r['mode']}", r["condition"]): r["effort"] for r in runs}
    effort_scores = effort_composite(metrics, effort, failed)
    table: dict[str, dict[str, Any]] = {}
    for law in config.laws:
        row: dict[str, Any] = {}
        for mode in config.modes:
            row[mode] = {
                "score": scores[f"{law}/{mode}"],
                "time_per_cycle": timing[law][mode],
                "failed_conditions": sorted(k for c, k in failed if c == f"{law}/{mode}"),
                "score_effort": effort_scores[f"{law}/{mode}"],
                "not_deployable_conditions": sorted(
                    r["condition"]
                    for r in runs
                    if r["law"] == law and r["mode"] == mode and not r["verdict"]["deployable"]
                ),
            }
            if mode != "fb" and "fb" in config.modes:
                row[mode]["eta"] = improvement(scores[f"{law}/{mode}"], scores[f"{law}/fb"])
                row[mode]["eta_effort"] = improvement(effort_scores[f"{law}/{mode}"], effort_scores[f"{law}/fb"])
        table[law] = row
    return {
        "robot": robot.name,
        "config": {
            "laws": list(config.laws),
            "modes": list(config.modes),
            "gain_set": config.gain_set,
            "sim": asdict(config.sim),
            "realism": config.realism,
        },
        "law_params": {law: make_law(law, robot, config.sim.period_s, config.gain_set).params for law in config.laws},
        "conditions": [
            {
                "name": c.name,
                "amplitude_rad": list(c.amplitude_rad),
                "frequency_hz": list(c.frequency_hz),
                "duration_s": c.duration_s,
                "initial_state": c.initial_state,
                "disturbance": None if c.disturbance is None else asdict(c.disturbance),
                "mismatch": asdict(c.mismatch),
            }
            for c in conditions
        ],
        "metric_names": list(METRICS),
        "table": table,
        "all_runs_finite_and_within_limits": all(r["finite"] and r["within_limits"] for r in runs),
        "runs": runs,
        "machine": machine("numpy", "pin", "torch"),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


_MODE_TITLE = {"fb": "FB", "hmpc": "HMPC", "lmpc": "LMPC"}
_ETA_TITLE = {"hmpc": "η_H (%)", "lmpc": "η_L (%)"}
_T_TITLE = {"fb": "t_FB (ms)", "hmpc": "t_H (ms)", "lmpc": "t_L (ms)"}


def format_table(results: dict[str, Any]) -> str:
    """Markdown in the layout of the paper's Table I (composite scores, eta, time per cycle)."""
    modes = results["config"]["modes"]
    head = ["Controller"]
    for mode in modes:
        head.append(_MODE_TITLE.get(mode, mode))
        if mode in _ETA_TITLE and "fb" in modes:
            head.append(_ETA_TITLE[mode])
    head += [_T_TITLE.get(m, m) for m in modes]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    etas: dict[str, list[float]] = defaultdict(list)
    for law, row in results["table"].items():
        cells = [LAW_TITLES.get(law, law)]
        for mode in modes:
            failed = row[mode].get("failed_conditions", [])
            mark = f" ✗{len(failed)}" if failed else ""
            score = row[mode]["score"]
            cells.append(f"{score:.3f}{mark}" if score < 1e3 else f"{score:.1e}{mark}")
            if "eta" in row[mode]:
                if failed or row["fb"].get("failed_conditions"):
                    cells.append("—")  # eta against or of a run that left the limits means nothing
                else:
                    cells.append(f"{100 * row[mode]['eta']:.1f}")
                    etas[mode].append(row[mode]["eta"])
        cells += [f"{row[m]['time_per_cycle']['median_ms']:.4f}" for m in modes]
        lines.append("| " + " | ".join(cells) + " |")
    notes = [
        f"Average {_ETA_TITLE[m]} over laws whose runs all stayed inside the limits: {100 * float(np.mean(v)):.1f}"
        for m, v in etas.items()
    ]
    limits = "yes" if results["all_runs_finite_and_within_limits"] else "NO (see results.json runs)"
    rate_limit = (results.get("controller_options") or {}).get("lmpc", {}).get("torque_rate_limit")
    if rate_limit is not None:  # docs/lmpc.md section 10: the LMPC's output rate limit, opt-in
        notes.append(f"LMPC torque-rate limit: {rate_limit} (hil_runtime.rate_limit).")
    footer = [
        "",
        f"Robot {results['robot']}; conditions: {', '.join(c['name'] for c in results['conditions'])}; "
        f"control period {results['config']['sim']['period_s'] * 1e3:g} ms; "
        f"gain set '{results['config']['gain_set']}'.",
        "Scores: composite of the six metrics, each normalized per condition by its largest value among the "
        "configurations in this table (docs/scoring.md). Times: median wall time per control cycle, one robot.",
        f"Every run finite and inside the joint limits: {limits}. ✗k: k conditions diverged or left the limits "
        "(excluded from the normalization; η shown as —).",
        *notes,
        "",
    ]
    return "\n".join(lines + footer + format_effort_table(results))
