"""The paper's Table II as hardware-in-the-loop: ``hil experiment --plant hil``.

For each law, mode (``fb``, ``lmpc``) and condition, the real runtime loop
(:class:`hil_runtime.runtime.Runtime`) runs the shipped bundle against the pybullet target
(sim_target) in lock-step over the CAN bus; the target places the arm on the condition's initial
state when the drives are enabled and injects the condition's disturbance; the trajectory is the
runtime's own record; it is scored by the simulation's scoring code (models.scoring, the same
normalization as ``hil experiment``).

Parity (unless ``parity=False``): the simulation of the same laws, modes and conditions runs in a
second process meanwhile (``out_dir/sim/``, a complete ``hil experiment`` output), and every run is
compared with its simulated twin: composite score difference and trajectory RMS difference
(docs/hil.md says why they differ).

Outputs in ``out_dir``, as ``hil experiment``:
  results.json   raw metrics per run, composite scores, eta, runtime compute per cycle, parity
  table.md       the layout of the paper's Table II (FB -> LMPC per law, the paper's values beside),
                 then the parity table
  trajectories/  one .npz per run: the runtime's record (t, q, qd, q_ref, qd_ref, tau, tau_fb, ...)
  plots/         tracking errors (as the simulation's), plots/parity/ HIL vs simulation
  sim/           the simulation's own outputs (parity)
  bundles/       the bundles both ran, copied at the start (a re-export meanwhile changes nothing)
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from hil_runtime.outputs import write_text_atomic
from models.conditions import Condition
from models.errors import ModelInputError
from models.experiment import ExperimentConfig, run_experiment, summarize, write_outputs
from models.robots import RobotModel
from models.scoring import run_metrics

HIL_MODES = ("fb", "lmpc")
#: The paper's Table II (hardware): FB score -> LMPC score per law.
PAPER_TABLE_II: dict[str, tuple[float, float]] = {
    "pd": (0.997, 0.661),
    "pid": (0.728, 0.246),
    "adrc": (0.278, 0.124),
    "hinf": (0.234, 0.090),
    "smc": (0.245, 0.007),
    "mrac": (0.046, 0.013),
}
PARITY_TOLERANCE = 0.05  # the budget: HIL within 5 % of the simulation
# Bounds on waits for frames, not assertions on time: a lock-stepped target does not care about
# wall time, and on a shared 2-core machine a niced experiment was measured stalled for over 1 s
# (a feedback timeout of 50 ms and a heartbeat timeout of 1 s then faulted runs that were fine).
# The drives' own master-loss watch (comm_loss_timeout_s) stays on: a dead experiment process
# still leaves the arm quick-stopped, after 10 s.
DRIVER_TIMEOUTS = {
    "feedback_timeout_s": 2.0,
    "heartbeat_timeout_s": 10.0,
    "sdo_timeout_s": 5.0,
    "state_change_timeout_s": 10.0,
    "comm_loss_timeout_s": 10.0,
}
# Faults of the rig, not of the controller (a lock-stepped run's result cannot depend on them):
# such a run is run again, up to RIG_RETRIES times, and the retries are counted in results.json.
RIG_FAULTS = ("feedback_timeout", "heartbeat_lost", "transport", "drive_state", "stale_feedback")
RIG_RETRIES = 2
CHUNK_CYCLES = 250  # the loop runs in chunks of this many cycles so the progress bar moves


@dataclass(frozen=True)
class HilOptions:
    transport: str = "virtual"  # virtual (one process) | ipc | bridge (the target in its own process)
    target_substeps: int = 32  # pybullet steps per control period (docs/hil.md: integration)
    parity: bool = True  # also simulate, compare run by run
    bundle_dir: Path | None = None  # LMPC/FB bundles; None: models/bundles (the shipped ones)


@dataclass
class HilRun:
    """One run's record (the runtime's arrays, padded to the condition's length when it faulted)."""

    arrays: dict[str, np.ndarray]
    rows: int  # rows the runtime recorded (< steps when it faulted)
    fault: str | None
    stats: dict[str, Any]
    rig_retries: int = 0  # runs done again after a fault of the rig (RIG_FAULTS)

    @property
    def rig_fault(self) -> bool:
        return self.fault is not None and self.fault.split(":", 1)[0] in RIG_FAULTS


# --- conditions and configs --------------------------------------------------------------------------


def conditions_yaml(conditions: list[Condition]) -> str:
    """The conditions in the runtime's YAML format (hil_runtime/conditions.py), exactly (repr floats)."""

    def plain(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items() if v is not None}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        return float(value) if isinstance(value, (float, np.floating)) else value

    items = []
    for c in conditions:
        item = plain(asdict(c))  # a None field (no disturbance, no offset) is left out: None when read
        if c.mismatch.is_nominal:
            item.pop("mismatch", None)
        items.append(item)
    return yaml.safe_dump({"conditions": items}, sort_keys=False)


def initial_state(condition: Condition) -> tuple[np.ndarray, np.ndarray]:
    """(q0, qd0) as the simulator starts (models.sim.closed_loop.simulate)."""
    q0 = np.asarray(condition.initial_position(), float)
    if condition.initial_state == "reference":
        return q0, np.asarray(condition.reference(0.0)[1], float)
    return q0, np.zeros_like(q0)


def run_start(condition: Condition) -> dict[str, Any]:
    """The target's RunStart for ``condition``: its initial state, its disturbance (if any)."""
    q0, qd0 = initial_state(condition)
    faults = []
    d = condition.disturbance
    if d is not None and d.duration_s > 0 and any(t != 0 for t in d.torque_nm):
        faults.append({"kind": "impulse", "at_s": d.time_s, "duration_s": d.duration_s, "torque_nm": list(d.torque_nm)})
    return {"kind": "start", "position_rad": q0.tolist(), "velocity_rad_s": qd0.tolist(), "faults": faults}


def runtime_config_dict(
    robot: RobotModel,
    bundle: Path,
    mode: str,
    transport: dict[str, Any],
    period_s: float,
    conditions_file: Path,
    condition: str,
) -> dict[str, Any]:
    """The runtime's config for one run: lock-step (bus pacing), no ramp (the arm is placed)."""
    joints = [
        {"name": name, "node_id": i + 1, "max_torque_nm": float(t)}
        for i, (name, t) in enumerate(zip(robot.joint_names, robot.torque_limit_nm, strict=True))
    ]
    return {
        "robot": robot.name,
        "bundle": {"path": str(bundle), "mode": mode},
        "bus": {"transport": transport, "period_s": period_s, "joints": joints, **DRIVER_TIMEOUTS},
        "reference": {
            "kind": "condition",
            "conditions_file": str(conditions_file),
            "condition": condition,
            "start": "condition",
        },
        "loop": {"pacing": "bus", "time_base": "cycles", "stats_interval_s": 3600.0},
    }


def check_hil_inputs(
    robot: RobotModel, conditions: list[Condition], config: ExperimentConfig, options: HilOptions
) -> None:
    """Refuse what the HIL plant cannot do, with one line each (exit 2)."""
    from models.lmpc.controller import bundle_path
    from models.robots.description import robot_names
    from sim_target.launch import TRANSPORTS

    bad_modes = [m for m in config.modes if m not in HIL_MODES]
    if bad_modes:
        raise ModelInputError(
            f"--modes: '{bad_modes[0]}' cannot run on --plant hil (the runtime runs bundles: {', '.join(HIL_MODES)})"
        )
    if options.transport not in TRANSPORTS:
        raise ModelInputError(f"--transport: unknown '{options.transport}' (known: {', '.join(TRANSPORTS)})")
    if options.target_substeps < 1:
        raise ModelInputError(f"--target-substeps: must be >= 1, got {options.target_substeps}")
    if robot.name not in robot_names():
        raise ModelInputError(f"--robot: --plant hil needs a built-in robot (known: {', '.join(robot_names())})")
    for c in conditions:
        if not c.mismatch.is_nominal:
            raise ModelInputError(
                f"condition {c.name}: plant-model mismatch is not emulated by the HIL target "
                "(it runs the nominal URDF): use --mismatch none"
            )
    for law in config.laws:
        path = bundle_path(robot.name, law, options.bundle_dir)
        manifest = path / "manifest.json"
        if not manifest.is_file():
            raise ModelInputError(f"{manifest}: no bundle for law '{law}' (export one with `hil pipeline`)")
        gain_set = json.loads(manifest.read_text())["law"].get("gain_set")
        if gain_set != config.gain_set:
            raise ModelInputError(
                f"{manifest}: bundle exported with gain set '{gain_set}', --gains is "
                f"'{config.gain_set}' (the runtime runs the bundle's law)"
            )


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


# --- one run ---------------------------------------------------------------------------------------


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
    retries = 0
    while True:
        run = _run_once(target, robot, law, mode, condition, period_s, options, conditions_file, advance)
        if not run.rig_fault or retries >= RIG_RETRIES:
            run.rig_retries = retries
            return run
        retries += 1


def _run_once(
    target: Any,
    robot: RobotModel,
    law: str,
    mode: str,
    condition: Condition,
    period_s: float,
    options: HilOptions,
    conditions_file: Path,
    advance: Callable[[int], None] | None,
) -> HilRun:
    from drivers.drive_bus import DriveBus
    from hil_runtime.config import parse_runtime_config
    from hil_runtime.runtime import Runtime
    from models.lmpc.controller import bundle_path
    from sim_target.config import parse_run_start

    steps = int(round(condition.duration_s / period_s))
    data = runtime_config_dict(
        robot,
        bundle_path(robot.name, law, options.bundle_dir),
        mode,
        target.transport,
        period_s,
        conditions_file,
        condition.name,
    )
    config = parse_runtime_config(data, f"hil experiment {law}/{mode}/{condition.name}")
    runtime = Runtime(config, DriveBus(config.bus), record_cycles=steps)
    fault: str | None = None
    shown = 0  # periods shown on the progress bar for this run
    try:
        runtime.configure()
        target.start_run(parse_run_start(run_start(condition), "start"))
        if runtime.activate():
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
    record = {k: np.array(v) for k, v in runtime.record.arrays().items()}
    run = HilRun(_pad(record, steps, period_s), int(record["q"].shape[0]), fault, stats)
    if advance is not None:  # a rig fault runs again: take its periods back; else count the rest as done
        advance(-shown if run.rig_fault else steps - 1 - shown)
    return run


def _pad(record: dict[str, np.ndarray], steps: int, period_s: float) -> dict[str, np.ndarray]:
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


def _run_record(
    robot: RobotModel, law: str, mode: str, condition: Condition, run: HilRun, steps: int
) -> dict[str, Any]:
    a = run.arrays
    dist_time = None if condition.disturbance is None else condition.disturbance.time_s
    finite = bool(np.isfinite(a["q"]).all() and np.isfinite(a["qd"]).all())
    position_ratio = float(np.max(robot.position_limit_ratio(a["q"]))) if finite else math.inf
    velocity_ratio = float(np.max(np.abs(a["qd"]) / robot.velocity_limit_rad_s)) if finite else math.inf
    stats = run.stats
    compute_us = a["compute_s"][1 : run.rows] * 1e6 if run.rows > 1 else np.zeros(1)
    return {
        "law": law,
        "mode": mode,
        "condition": condition.name,
        "metrics": run_metrics(a["t"], a["q"], a["q_ref"], dist_time),
        "finite": finite,
        "within_limits": finite and run.fault is None and position_ratio <= 1.0 and velocity_ratio <= 1.0,
        "position_limit_ratio": position_ratio,
        "velocity_limit_ratio": velocity_ratio,
        "max_abs_torque_nm": np.abs(a["tau"]).max(axis=0).tolist(),
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
        },
    }


# --- the experiment ----------------------------------------------------------------------------------


def _simulate(
    robot_name: str, conditions: list[Condition], config: ExperimentConfig, out_dir: Path, bundle_dir: Path | None
) -> None:
    """The simulation twin (``hil experiment --modes fb,lmpc``) in a second process: writes out_dir."""
    from models.robots import load_robot

    options = {"lmpc": {"bundle_dir": bundle_dir}} if bundle_dir is not None else None
    run_experiment(load_robot(robot_name), conditions, config, out_dir, controller_options=options)


def run_hil_experiment(
    robot: RobotModel,
    conditions: list[Condition],
    config: ExperimentConfig,
    out_dir: Path,
    options: HilOptions = HilOptions(),
    progress: Callable[[str, int], Callable[[int], None]] | None = None,
) -> dict[str, Any]:
    """Run every (law, mode, condition) on the HIL target; write the outputs; return the results.

    ``progress(label, total)`` returns a callable advancing a progress bar (periods).
    """
    from sim_target.launch import launch_target, target_config_dict

    check_hil_inputs(robot, conditions, config, options)
    out_dir.mkdir(parents=True, exist_ok=True)
    # One snapshot of the bundles for the HIL runs and the simulation twin alike: a bundle
    # re-exported while the experiment runs (it happened) must not mix two versions in one table.
    options = replace(options, bundle_dir=snapshot_bundles(robot, config.laws, options.bundle_dir, out_dir / "bundles"))
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
            args=(robot.name, conditions, sim_config, sim_dir, options.bundle_dir),
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
        target_config = target_config_dict(robot.name, period_s, options.target_substeps)
        with launch_target(target_config, options.transport) as target:  # type: ignore[arg-type]
            for law in config.laws:
                for mode in config.modes:
                    for condition in conditions:
                        run = run_on_target(
                            target, robot, law, mode, condition, period_s, options, conditions_file, advance
                        )
                        runs.append(_run_record(robot, law, mode, condition, run, steps[condition.name]))
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
        "target_substeps": options.target_substeps,
        "period_s": period_s,
        "wall_s": round(hil_wall_s, 1),
        "simulated_s": round(sum(steps.values()) * period_s * len(config.laws) * len(config.modes), 1),
        "time_columns": "runtime compute per cycle (feedback in -> set-points out: supervisor, reference, one "
        "onnxruntime call, record), median over every cycle of the law's runs",
        "paper_table_ii": {law: {"fb": v[0], "lmpc": v[1]} for law, v in PAPER_TABLE_II.items()},
        "bundles": {law: _bundle_digest(options.bundle_dir / law) for law in config.laws},  # type: ignore[operator]
    }
    if sim_results is not None:
        results["parity"] = parity(results, sim_results, trajectories, sim_dir / "trajectories")

    def parity_plots(plots_dir: Path) -> None:
        if "parity" in results:
            plot_parity(results, trajectories, sim_dir / "trajectories", plots_dir / "parity")

    write_outputs(
        out_dir, config, conditions, trajectories, format_hil_table(results), _json_safe(results), parity_plots
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


def _json_safe(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


# --- parity with the simulation ----------------------------------------------------------------------


def _per_run_scores(
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
    sim_scores = _per_run_scores(sim["runs"])
    hil_scores = _per_run_scores(hil["runs"], scale=sim["runs"])
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
            h_score = float(np.mean([p["score_hil"] for p in mine]))
            s_score = float(np.mean([p["score_sim"] for p in mine]))
            table[law][mode] = {
                "score_hil": h_score,
                "score_sim": s_score,
                "score_rel": _relative(h_score, s_score),
                "score_hil_own_table": row[mode]["score"],
                "score_sim_own_table": sim["table"][law][mode]["score"],
                "trajectory_rms_diff_deg": float(np.sqrt(np.mean([p["trajectory_rms_diff_deg"] ** 2 for p in mine]))),
                "trajectory_rms_diff_rel_to_sim_rmse": max(p["trajectory_rms_diff_rel_to_sim_rmse"] for p in mine),
                "within_tolerance": abs(_relative(h_score, s_score)) <= PARITY_TOLERANCE,
            }
    return {
        "tolerance": PARITY_TOLERANCE,
        "table": table,
        "runs": per_run,
        "sim_config": sim["config"],
        "sim_all_runs_within_limits": sim["all_runs_finite_and_within_limits"],
    }


# --- tables and plots ----------------------------------------------------------------------------------

_LAW_TITLE = {"pd": "PD", "pid": "PID", "adrc": "ADRC", "hinf": "H∞", "smc": "SMC", "mrac": "MRAC"}


def format_hil_table(results: dict[str, Any]) -> str:
    """Table II's layout (FB -> LMPC per law, the paper's beside), then the parity table."""
    modes = results["config"]["modes"]
    hil = results["hil"]
    times = " | ".join(f"t_{'L' if m == 'lmpc' else 'FB'} (µs)" for m in modes)
    eta = " | η_L (%)" if {"fb", "lmpc"} <= set(modes) else ""
    lines = ["| Controller | " + " | ".join(m.upper() for m in modes) + eta + " | paper FB → LMPC | " + times + " |"]
    lines.append("|" + "---|" * (lines[0].count("|") - 1))
    for law, row in results["table"].items():
        cells = [_LAW_TITLE.get(law, law)]
        for mode in modes:
            failed = row[mode].get("failed_conditions", [])
            cells.append(f"{row[mode]['score']:.3f}" + (f" ✗{len(failed)}" if failed else ""))
        if "eta" in row.get("lmpc", {}):
            bad = row["lmpc"].get("failed_conditions") or row["fb"].get("failed_conditions")
            cells.append("—" if bad else f"{100 * row['lmpc']['eta']:.1f}")
        paper = PAPER_TABLE_II.get(law)
        cells.append(f"{paper[0]:.3f} → {paper[1]:.3f}" if paper else "—")
        cells += [f"{row[m]['time_per_cycle']['median_ms'] * 1e3:.1f}" for m in modes]
        lines.append("| " + " | ".join(cells) + " |")
    limits = "yes" if results["all_runs_finite_and_within_limits"] else "NO (see results.json runs)"
    lines += [
        "",
        f"HIL: the runtime (hil_runtime) drives the pybullet target over CAN ({hil['transport']} transport), "
        f"lock-stepped at {hil['period_s'] * 1e3:g} ms, {hil['target_substeps']} physics substeps per period; "
        f"{hil['simulated_s']:g} s simulated in {hil['wall_s']:g} s. Robot {results['robot']}; conditions: "
        f"{', '.join(c['name'] for c in results['conditions'])}; gain set '{results['config']['gain_set']}'.",
        "Scores: the simulation's composite (docs/scoring.md), normalized per condition among the runs of this "
        "table. t: the runtime's compute per cycle (feedback in → set-points out), median.",
        f"Every run finite and inside the joint limits: {limits}. ✗k: k conditions faulted or left the limits.",
        "",
    ]
    if "parity" in results:
        lines += format_parity_table(results["parity"], modes)
    return "\n".join(lines)


def format_parity_table(parity_results: dict[str, Any], modes: list[str]) -> list[str]:
    head = ["Controller"]
    for mode in modes:
        m = mode.upper()
        head += [f"{m} sim", f"{m} HIL", f"{m} Δ (%)", f"{m} traj. RMS Δ (deg)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    worst = 0.0
    for law, row in parity_results["table"].items():
        cells = [_LAW_TITLE.get(law, law)]
        for mode in modes:
            p = row[mode]
            worst = max(worst, abs(p["score_rel"]))
            mark = "" if p["within_tolerance"] else " ⚠"
            cells += [
                f"{p['score_sim']:.3f}",
                f"{p['score_hil']:.3f}",
                f"{100 * p['score_rel']:+.1f}{mark}",
                f"{p['trajectory_rms_diff_deg']:.4f}",
            ]
        lines.append("| " + " | ".join(cells) + " |")
    tol = 100 * parity_results["tolerance"]
    return lines + [
        "",
        f"Parity: HIL vs the simulation (`hil experiment --modes {','.join(modes)}`, RK4, same conditions), both "
        "scored on the simulation's scale (its per-condition maxima), so a law's Δ is its own runs' difference. "
        f"Largest |Δ| {100 * worst:.1f} % (budget {tol:g} %; ⚠ beyond it). Traj. RMS Δ: RMS over time and joints of "
        "q_HIL − q_sim, over the law's runs; docs/hil.md explains the differences.",
        "",
    ]


def plot_parity(
    results: dict[str, Any],
    trajectories: dict[tuple[str, str, str], dict[str, np.ndarray]],
    sim_traj_dir: Path,
    out_dir: Path,
) -> list[Path]:
    """Score difference per law and mode; per law, HIL vs simulation error on the worst condition."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from models.plots import save_figure

    out_dir.mkdir(parents=True, exist_ok=True)
    par = results["parity"]
    laws = list(par["table"])
    modes = results["config"]["modes"]
    written = []

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    width = 0.8 / len(modes)
    for i, mode in enumerate(modes):
        x = np.arange(len(laws)) + (i - (len(modes) - 1) / 2) * width
        axes[0].bar(x, [100 * par["table"][law][mode]["score_rel"] for law in laws], width, label=mode.upper())
        axes[1].bar(x, [par["table"][law][mode]["trajectory_rms_diff_deg"] for law in laws], width, label=mode.upper())
    for ax, title in zip(axes, ("composite score, HIL vs sim (%)", "trajectory RMS difference (deg)"), strict=True):
        ax.set_xticks(np.arange(len(laws)), [_LAW_TITLE.get(law, law) for law in laws])
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3, axis="y")
        ax.legend(fontsize=8)
    tol = 100 * par["tolerance"]
    axes[0].axhspan(-tol, tol, color="green", alpha=0.1)
    fig.tight_layout()
    path = out_dir / "parity_scores.png"
    written.append(save_figure(fig, path))

    for mode in modes:
        fig, axes = plt.subplots(len(laws), 1, figsize=(9, 1.9 * len(laws) + 0.6), sharex=True, squeeze=False)
        for ax, law in zip(axes[:, 0], laws, strict=True):
            mine = [p for p in par["runs"] if p["law"] == law and p["mode"] == mode]
            worst = max(mine, key=lambda p: abs(p["score_rel"]))
            cond = worst["condition"]
            h = trajectories[(law, mode, cond)]
            s = np.load(sim_traj_dir / f"{law}_{mode}_{cond}.npz")
            ax.plot(s["t"], np.abs(np.degrees(s["q_ref"] - s["q"])).mean(axis=1), lw=1, label="sim")
            ax.plot(h["t"], np.abs(np.degrees(h["q_ref"] - h["q"])).mean(axis=1), "--", lw=1, label="HIL")
            ax.plot(h["t"], np.abs(np.degrees(h["q"] - s["q"])).mean(axis=1), lw=0.8, color="k", label="|HIL − sim|")
            ax.set_yscale("log")
            ax.set_ylim(bottom=1e-5)
            ax.set_ylabel("deg", fontsize=8)
            ax.set_title(
                f"{_LAW_TITLE.get(law, law)} {mode.upper()} {cond}: score Δ {100 * worst['score_rel']:+.1f} %",
                fontsize=9,
            )
            ax.grid(alpha=0.3, which="both")
        axes[0, 0].legend(fontsize=7, ncol=3)
        axes[-1, 0].set_xlabel("t (s)")
        fig.suptitle(f"{mode.upper()}: mean |e| over joints, HIL vs simulation (worst condition per law)", fontsize=10)
        fig.tight_layout()
        path = out_dir / f"parity_error_{mode}.png"
        written.append(save_figure(fig, path))
    return written


__all__ = [
    "HIL_MODES",
    "PAPER_TABLE_II",
    "HilOptions",
    "format_hil_table",
    "parity",
    "run_hil_experiment",
    "run_on_target",
    "conditions_yaml",
]
