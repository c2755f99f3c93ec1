"""Stage ``augment`` (beyond the paper, docs/lmpc.md): the deployed emulators, trained on a residual
target with on-policy data (HMPC rollouts, DAgger rounds), and the per-law trust-region choice."""

from __future__ import annotations

import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from hil_runtime.bundle_schema import GUARD_FEATURES
from models.executors import Executor
from models.feedback import make_law
from models.lmpc.dataset import RawLaw, load_raw_dataset
from models.lmpc.emulator import train_emulator
from models.lmpc.labels import hmpc_labeler
from models.lmpc.pipeline.config import PipelineConfig, Progress, progress_callback
from models.lmpc.pipeline.export import export_deployed
from models.lmpc.pipeline.labeling import load_labels
from models.lmpc.sampling import (
    region_index,
)
from models.robots import load_robot


def _augmented_task(task: tuple) -> dict[str, Any]:
    law, x, y, train_config = task
    result = train_emulator(x, y, train_config)
    return {
        "law": law,
        "summary": result.summary(),
        "state_dict": {k: v.numpy() for k, v in result.emulator.state_dict().items()},
    }


def theorem2_repeats(t_s: np.ndarray, weights: np.ndarray, base: int) -> np.ndarray:
    """Per-sample repeat counts that give each time region its Theorem 2 weight w_i* of the samples.

    With A_i the region's share of the on-policy samples, a sample of region i is repeated
    base * round((w_i / A_i) / min_j (w_j / A_j)) times (regions without samples are ignored).
    """
    region = region_index(t_s)
    shares = np.array([(region == i).mean() for i in range(len(weights))])
    ratio = np.where(shares > 0, np.asarray(weights, float) / np.maximum(shares, 1e-12), np.inf)
    finite = np.isfinite(ratio)
    per_region = base * np.maximum(1, np.round(np.where(finite, ratio, 1.0) / ratio[finite].min())).astype(int)
    return np.where(region >= 0, per_region[np.clip(region, 0, None)], base)


def _residual_set(feature_set: str, rows: Any, tau_star: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from hil_runtime.trust_region import emulator_features

    x = emulator_features(feature_set, rows["q"], rows["qd"], rows["q_d"], rows["qd_d"], rows["qdd_d"], rows["tau_fb"])
    return x, np.asarray(tau_star, float) - np.asarray(rows["tau_fb"], float)


def _rows(raw_law: RawLaw) -> dict[str, np.ndarray]:
    return {k: getattr(raw_law, k) for k in ("t_s", "q", "qd", "q_d", "qd_d", "qdd_d", "tau_fb", "law_state")}


def stage_augment(
    config: PipelineConfig, work: Path, executor: Executor, progress: Progress | None = None
) -> dict[str, Any]:
    """The deployed emulators: residual target, on-policy data (HMPC rollouts + DAgger rounds), trust region.

    1. HMPC closed-loop rollouts on ``rollout_conditions`` pool conditions (0 .. ``rollout_duration_s``,
       the disturbance inside), labeled with the torque the HMPC applied (cached in
       <work>/expert_rollouts.pkl with the settings that made them).
    2. Training set = D_sample (Theorem 2) + the rollouts, the on-policy samples repeated per time
       region so that the regions get the Theorem 2 weights (``theorem2_repeats``); target
       tau* - tau_fb; features ``feature_set``.
    3. ``dagger_rounds`` times: export, run the LMPC on ``dagger_conditions`` pool conditions, label
       the visited in-limit states with the HMPC (cold solves), add them, retrain.
    """
    import pickle

    from models.lmpc.dagger import lmpc_visited_states
    from models.lmpc.dataset import make_conditions
    from models.lmpc.expert_rollouts import hmpc_rollouts
    from models.sim import SimConfig

    spec = config.dataset
    robot = load_robot(spec.robot)
    raw = load_raw_dataset(work / "raw.h5", config.laws)
    _, labels = load_labels(work / "labels.h5")
    pool = make_conditions(spec, robot)[: config.pool_conditions]
    sim = SimConfig(period_s=spec.period_s, substeps=spec.substeps)
    train_config = replace(
        config.train,
        hidden=config.deploy_hidden,
        max_epochs=config.augment_epochs,
        seed=config.seeds[0],
        center_targets=False,
    )
    steps = 2 + 2 * config.dagger_rounds
    advance = progress_callback(progress, "augment: HMPC rollouts, DAgger rounds, training", steps)
    wall: dict[str, float] = {}
    started = time.perf_counter()
    key = {
        "robot": spec.robot,
        "laws": list(config.laws),
        "gain_set": spec.gain_set,
        "seed": spec.seed,
        "conditions": config.rollout_conditions,
        "duration_s": config.rollout_duration_s,
        "stride": config.rollout_stride,
        "initial_state": config.rollout_initial_state,
    }
    cache = work / "expert_rollouts.pkl"
    rollouts = None
    if cache.is_file():
        with open(cache, "rb") as handle:
            cached = pickle.load(handle)
        if isinstance(cached, dict) and cached.get("key") == key:
            rollouts, wall["rollouts_cached_s"] = cached["data"], cached["wall_s"]
    if rollouts is None:
        conditions = [
            replace(c, duration_s=config.rollout_duration_s, initial_state=config.rollout_initial_state)
            for c in pool[: config.rollout_conditions]
        ]
        rollouts = hmpc_rollouts(
            spec.robot,
            config.laws,
            spec.gain_set,
            conditions,
            sim,
            stride=config.rollout_stride,
            chunks=max(2, config.workers or os.cpu_count() or 1),
            executor=executor,
        )
        wall["rollouts_s"] = round(time.perf_counter() - started, 1)
        with open(cache, "wb") as handle:
            pickle.dump({"key": key, "data": rollouts, "wall_s": wall["rollouts_s"]}, handle)
    advance(1)
    fs = config.feature_set
    data: dict[str, tuple[list, list]] = {}
    kept: dict[str, Any] = {}

    guards: dict[str, list[np.ndarray]] = {}

    def on_policy(rows: dict[str, np.ndarray], tau: np.ndarray, law: str) -> tuple[np.ndarray, np.ndarray, int]:
        keep = np.all(np.abs(rows["q_d"] - rows["q"]) <= config.on_policy_max_error_rad, 1)
        kept_rows = {k: v[keep] for k, v in rows.items()}
        x, y = _residual_set(fs, kept_rows, np.asarray(tau)[keep])
        guards.setdefault(law, []).append(_residual_set(GUARD_FEATURES, kept_rows, np.asarray(tau)[keep])[0])
        rep = theorem2_repeats(rows["t_s"][keep], labels[law].theorem2["weights"], config.augment_repeat)
        return np.repeat(x, rep, 0), np.repeat(y, rep, 0), int(keep.sum())

    for law in config.laws:
        x1, y1, kept[law] = on_policy(rollouts[law], rollouts[law]["tau_star"], law)
        data[law] = ([x1], [y1])
        if config.deploy_use_d_sample:
            idx = labels[law].sets["optimal"]
            x0, y0 = _residual_set(fs, _rows(raw.laws[law].take(idx)), labels[law].targets(idx))
            data[law][0].append(x0)
            data[law][1].append(y0)

    def train(parts: dict[str, tuple[list, list]]) -> dict[str, Any]:
        tasks = [
            (law, np.concatenate(parts[law][0]), np.concatenate(parts[law][1]), train_config) for law in config.laws
        ]
        results = {r["law"]: r for r in executor.map(_augmented_task, tasks)}
        for law, r in results.items():
            y, g = np.concatenate(parts[law][1]), np.concatenate(guards[law])
            r["box"] = (g.min(0), g.max(0))  # trust box: the guard features of the on-policy states
            gl = raw.laws[law].features(GUARD_FEATURES)[labels[law].sets["optimal"]]
            r["box_labeled"] = (np.minimum(g.min(0), gl.min(0)), np.maximum(g.max(0), gl.max(0)))
            r["samples"] = int(y.shape[0])
            r["residual_bound_nm"] = np.percentile(np.abs(y), config.residual_percentile, axis=0)
        return results

    def export(results: dict[str, Any], out: Path) -> None:
        for law, r in results.items():
            export_deployed(config, robot, law, r, out / robot.name / law, {"stage": "intermediate (DAgger)"}, {})

    results = train(data)
    advance(1)
    rng = np.random.default_rng(config.seeds[0])
    dagger_counts: list[dict[str, Any]] = []
    for round_ in range(config.dagger_rounds):
        out = work / f"bundles_dagger{round_}"
        export(results, out)
        conditions = [
            replace(c, duration_s=config.dagger_duration_s, initial_state=config.rollout_initial_state)
            for c in pool[config.rollout_conditions : config.rollout_conditions + config.dagger_conditions]
        ]
        visited = lmpc_visited_states(out, robot, config.laws, conditions, sim, spec.stride, spec.gain_set)
        advance(1)
        counts = {}
        for law in config.laws:
            rows = visited[law]
            if len(rows) > config.dagger_states_per_law:
                rows = rows.take(np.sort(rng.choice(len(rows), config.dagger_states_per_law, replace=False)))
            counts[law] = {"visited_in_limits": len(visited[law]), "labeled": len(rows)}
            if len(rows):
                tau, _ = hmpc_labeler(make_law(law, robot, spec.period_s, spec.gain_set), robot, rows, executor)
                x, y, counts[law]["kept"] = on_policy(_rows(rows), tau, law)
                data[law][0].append(x)
                data[law][1].append(y)
        dagger_counts.append(counts)
        results = train(data)
        advance(1)
    selection = {}
    first = config.rollout_conditions + config.dagger_conditions
    if config.trust_candidates and first < len(pool):
        conditions = [
            replace(c, duration_s=config.selection_duration_s, initial_state=config.rollout_initial_state)
            for c in pool[first : first + config.selection_conditions]
        ]
        selection = select_margins(config, robot, results, conditions, sim, work / "bundles_select")
        for law, r in results.items():
            kind, r["box_margin"] = selection[law]["chosen"]
            r["box_kind"] = kind
            if kind == "labeled":
                r["box"] = r["box_labeled"]
    wall["total_s"] = round(time.perf_counter() - started, 1)
    with open(work / "augmented.pkl", "wb") as handle:
        pickle.dump(results, handle)
    return {
        "rollout_conditions": config.rollout_conditions,
        "rollout_duration_s": config.rollout_duration_s,
        "rollout_states_per_law": {k: int(len(v["t_s"])) for k, v in rollouts.items()},
        "rollout_states_kept": kept,
        "feature_set": fs,
        "dagger": dagger_counts,
        "wall_s": wall,
        "margin_selection": selection,
        "samples": {law: r["samples"] for law, r in results.items()},
        "val_mse": {law: r["summary"]["best_val_mse_normalized"] for law, r in results.items()},
        "residual_bound_nm": {law: r["residual_bound_nm"].tolist() for law, r in results.items()},
    }


def select_margins(
    config: PipelineConfig, robot: Any, results: dict[str, Any], conditions: list, sim: Any, out: Path
) -> dict[str, Any]:
    """Per law, the trust region (box kind, margin) with the lowest closed-loop tracking RMSE on
    ``conditions`` (pool conditions: never the paper's) among the candidates whose runs all stay
    finite and inside the limits; the first candidate (mostly the feedback law) when none does."""
    from models.lmpc.controller import make_lmpc_controller
    from models.sim import simulate

    spec = config.dataset
    table: dict[str, Any] = {law: {"candidates": {}} for law in results}
    for i, (kind, margin) in enumerate(config.trust_candidates):
        for law, r in results.items():
            path = out / f"m{i}" / robot.name / law
            candidate = {**r, "box": r["box_labeled"] if kind == "labeled" else r["box"]}
            candidate.pop("box_margin", None)
            export_deployed(
                replace(config, box_margin=margin), robot, law, candidate, path, {"stage": "trust selection"}, {}
            )
            controller = make_lmpc_controller(
                make_law(law, robot, spec.period_s, spec.gain_set), robot, bundle_dir=path.parent.parent
            )
            with np.errstate(all="ignore"):
                traj = simulate(robot, controller, conditions, sim)
            ok = bool(np.all(traj.finite) and np.all(traj.within_limits))
            err = traj.q - traj.q_ref
            rmse = float(np.sqrt(np.mean(err**2))) if ok else float("inf")
            counts = controller.trust_counters()
            table[law]["candidates"][f"{kind}:{margin}"] = {
                "box": kind,
                "margin": margin,
                "rmse_rad": rmse,
                "inside_limits": ok,
                "fallback_share": float(np.mean(counts["fallback_cycles"])) / max(1, counts["cycles"]),
            }
    for row in table.values():
        scores = [(c["rmse_rad"], i, (c["box"], c["margin"])) for i, c in enumerate(row["candidates"].values())]
        best = min(scores)
        row["chosen"] = best[2] if np.isfinite(best[0]) else tuple(config.trust_candidates[0])
    return table
