"""``run_hil_experiment``: every (law, mode, condition) on the HIL target, the simulation twin in a
second process meanwhile, the results and outputs (models/hil_experiment/__init__.py lists them)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from hil_runtime.outputs import json_safe, write_text_atomic
from models.conditions import Condition
from models.errors import ModelInputError
from models.experiment import ExperimentConfig, run_experiment, summarize, write_outputs
from models.hil_experiment.config import HilOptions, check_hil_inputs, conditions_yaml
from models.hil_experiment.parity import parity
from models.hil_experiment.tables import PAPER_TABLE_II, format_hil_table, plot_parity
from models.hil_experiment.target_runs import run_on_target, run_record
from models.robot_target import robot_spec, target_robot_config
from models.robots import RobotModel

_DEFAULT_OPTIONS = HilOptions()


def snapshot_bundles(robot: RobotModel, laws: tuple[str, ...], bundle_dir: Path | None, into: Path) -> Path:
    """Copy each law's bundle (its directory's files) to ``into/<law>``; returns ``into``."""
    import shutil

    from models.lmpc.controller import bundle_path

    for law in laws:
        source = bundle_path(robot.name, law, bundle_dir)
        target = into / law
        if source.resolve() == target.resolve():
            continue
        if target.exists():
            shutil.rmtree(target)
        shutil.copytree(source, target)
    return into


def _simulate(
    robot_name: str,
    conditions: list[Condition],
    config: ExperimentConfig,
    out_dir: Path,
    bundle_dir: Path | None,
    torque_rate_limit: str = "none",
    velocity_filter_hz: float | None = None,
) -> None:
    """The simulation twin (``hil experiment --modes fb,lmpc``) in a second process: writes out_dir."""
    from models.robots import load_robot

    lmpc: dict[str, Any] = {"bundle_dir": bundle_dir} if bundle_dir is not None else {}
    if torque_rate_limit != "none":
        lmpc["torque_rate_limit"] = torque_rate_limit
    if velocity_filter_hz is not None:
        lmpc["velocity_filter_hz"] = velocity_filter_hz
    options = {"lmpc": lmpc} if lmpc else None
    run_experiment(load_robot(robot_name), conditions, config, out_dir, controller_options=options)


def run_hil_experiment(
    robot: RobotModel,
    conditions: list[Condition],
    config: ExperimentConfig,
    out_dir: Path,
    options: HilOptions = _DEFAULT_OPTIONS,
    progress: Callable[[str, int], Callable[[int], None]] | None = None,
) -> dict[str, Any]:
    """Run every (law, mode, condition) on the HIL target; write the outputs; return the results.

    ``progress(label, total)`` returns a callable advancing a progress bar (periods).
    """
    from models.lab.configs import target_config as lab_target_config
    from sim_target.launch import launch_target

    check_hil_inputs(robot, conditions, config, options)
    out_dir.mkdir(parents=True, exist_ok=True)
    # One snapshot of the bundles for the HIL runs and the simulation twin alike: a bundle
    # re-exported while the experiment runs (it happened) must not mix two versions in one table.
    bundles = snapshot_bundles(robot, config.laws, options.bundle_dir, out_dir / "bundles")
    options = replace(options, bundle_dir=bundles)
    period_s = config.sim.period_s
    conditions_file = out_dir / "conditions.yaml"
    write_text_atomic(conditions_file, conditions_yaml(conditions))
    sim_dir = out_dir / "sim"
    sim_process = None
    sim_advance = None
    if options.parity:
        # The simulation runs meanwhile on the other core: a separate process, no shared GIL.
        (sim_dir / "results.json").unlink(missing_ok=True)
        sim_config = replace(config, timing_cycles=min(config.timing_cycles, 200), save_trajectories=True)
        sim_process = get_context("spawn").Process(
            target=_simulate,
            args=(
                robot_spec(robot),
                conditions,
                sim_config,
                sim_dir,
                options.bundle_dir,
                options.torque_rate_limit,
                options.velocity_filter_hz,
            ),
            name="hil-experiment-sim",
            daemon=True,
        )
        sim_process.start()
        sim_advance = progress("simulation twin (second process)", 1) if progress else None
    started = time.monotonic()
    runs: list[dict[str, Any]] = []
    trajectories: dict[tuple[str, str, str], dict[str, np.ndarray]] = {}
    compute: dict[str, dict[str, list[np.ndarray]]] = {}
    steps = {c.name: int(round(c.duration_s / period_s)) for c in conditions}
    total = len(config.laws) * len(config.modes) * sum(s - 1 for s in steps.values())
    label = (
        f"hil ({options.transport}): {len(config.laws)} laws x {len(config.modes)} modes x {len(conditions)} conditions"
    )
    advance = progress(label, total) if progress else None
    try:
        # The target's physics on its own CPU when free-running, apart from the runtime's loop.
        realtime_cpus = options.cpus if options.clock == "realtime" else None
        target_config = target_robot_config(  # a URDF robot: its file and joints
            robot,
            lab_target_config(
                robot.name, period_s, options.target_substeps, realism=config.realism, realtime_cpus=realtime_cpus
            ),
        )
        with launch_target(target_config, options.transport) as target:
            for law in config.laws:
                for mode in config.modes:
                    for condition in conditions:
                        run = run_on_target(
                            target, robot, law, mode, condition, period_s, options, conditions_file, advance
                        )
                        runs.append(run_record(robot, law, mode, condition, run, steps[condition.name]))
                        trajectories[(law, mode, condition.name)] = run.arrays
                        compute.setdefault(law, {}).setdefault(mode, []).append(run.arrays["compute_s"][1 : run.rows])
        hil_wall_s = time.monotonic() - started
        sim_results = None
        if sim_process is not None:
            sim_process.join()
            if sim_process.exitcode != 0 or not (sim_dir / "results.json").is_file():
                raise ModelInputError(
                    f"the simulation twin failed (exit {sim_process.exitcode}); rerun with "
                    "--no-parity, or run `hil experiment --plant sim` to see why"
                )
            sim_results = json.loads((sim_dir / "results.json").read_text())
            if sim_advance is not None:
                sim_advance(1)
    finally:
        if sim_process is not None and sim_process.is_alive():  # interrupted: do not leave it running
            sim_process.terminate()
            sim_process.join(10)

    timing = {
        law: {mode: _timing(np.concatenate(parts)) for mode, parts in modes.items()} for law, modes in compute.items()
    }
    results = summarize(runs, timing, config, robot, conditions)
    results["plant"] = "hil"
    results["hil"] = {
        "transport": options.transport,
        "clock": options.clock,
        "torque_rate_limit": options.torque_rate_limit,
        "invalid_runs": [
            {k: r[k] for k in ("law", "mode", "condition", "invalid_reason")} for r in runs if not r.get("valid", True)
        ],
        "target_substeps": options.target_substeps,
        "period_s": period_s,
        "wall_s": round(hil_wall_s, 1),
        "simulated_s": round(sum(steps.values()) * period_s * len(config.laws) * len(config.modes), 1),
        "time_columns": "runtime compute per cycle (feedback in -> set-points out: supervisor, reference, one "
        "onnxruntime call, record), median over every cycle of the law's runs",
        "paper_table_ii": {law: {"fb": v[0], "lmpc": v[1]} for law, v in PAPER_TABLE_II.items()},
        "bundles": {law: _bundle_digest(bundles / law) for law in config.laws},
    }
    if sim_results is not None:
        results["parity"] = parity(results, sim_results, trajectories, sim_dir / "trajectories")

    def parity_plots(plots_dir: Path) -> None:
        if "parity" in results:
            plot_parity(results, trajectories, sim_dir / "trajectories", plots_dir / "parity")

    write_outputs(
        out_dir, config, conditions, trajectories, format_hil_table(results), json_safe(results), parity_plots
    )
    return results


def _bundle_digest(path: Path) -> dict[str, Any]:
    """Where the snapshot came from and the sha256 of its graph (the manifest lists every file's)."""
    manifest = json.loads((path / "manifest.json").read_text())
    files = manifest.get("files") or manifest.get("sha256") or {}
    return {
        "path": str(path),
        "law": manifest["law"]["name"],
        "gain_set": manifest["law"].get("gain_set"),
        "files_sha256": files,
    }


def _timing(compute_s: np.ndarray) -> dict[str, float]:
    ms = compute_s * 1e3 if compute_s.size else np.zeros(1)
    return {"median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)), "cycles": int(compute_s.size)}


__all__ = ["run_hil_experiment", "snapshot_bundles"]
