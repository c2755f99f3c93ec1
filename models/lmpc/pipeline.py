"""The LMPC pipeline: D_input -> Theorem 2 sampling -> HMPC labels -> emulators -> policy bundles.

Stages (each reads the previous stage's file, so any can be rerun alone):

    dataset   <work>/raw.h5        D_input (models.lmpc.dataset)
    label     <work>/labels.h5     per law: optimal, uniform and test indices into raw.h5, HMPC labels
    train     <work>/training.json optimal vs uniform, 3 seeds each; <work>/sampling_curves.png
    export    <bundles>/<robot>/<law>/{policy.onnx, manifest.json}

Splits: the conditions are split into a sampling pool (the first ``pool_conditions``) and held-out
conditions from which a fixed uniform test set is drawn; the samplers only see the pool. The budget
(100,000, the paper's) is shared equally by the six laws; each law gets its own emulator.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from hil_runtime.bundle import FEATURE_SETS, GUARD_FEATURES
from models.errors import ModelInputError
from models.executors import DEFAULT_EXECUTOR, Executor, make_executor
from models.feedback import make_law
from models.lmpc.dataset import RawDatasetSpec, RawLaw, generate_raw_dataset, git_commit, load_raw_dataset
from models.lmpc.emulator import TrainConfig, train_emulator
from models.lmpc.h5file import read_h5, write_h5, write_manifest
from models.lmpc.labels import LABEL_HMPC_OPTIONS, Labeler, hmpc_labeler
from models.lmpc.sampling import (
    PAPER_REGIONS,
    estimate_lipschitz_delta,
    optimal_sample,
    optimal_weights,
    region_index,
    time_proportions,
    uniform_sample,
)
from models.robots import load_robot

LABELS_SCHEMA = "hil-lmpc-labels/1"
Progress = Callable[[str, int], Callable[[int], None]]


@dataclass(frozen=True)
class PipelineConfig:
    dataset: RawDatasetSpec = RawDatasetSpec()
    budget: int = 100_000  # labeled samples over all laws (paper: 100,000 of 600,000)
    pool_conditions: int = 90  # conditions the samplers draw from; the rest give the test set
    test_per_law: int = 2000
    lipschitz_delta: str | tuple[float, ...] = (0.0, 0.0, 0.0)  # or "estimate"
    epsilon: float = 1e-9
    power: float = 1.0
    seeds: tuple[int, ...] = (0, 1, 2)
    train: TrainConfig = TrainConfig()
    label_chunk: int = 2048  # states per progress update
    # Beyond the paper (docs/lmpc.md): the deployed emulators (augment stage): residual target,
    # HMPC closed-loop rollouts + DAgger rounds, trust region.
    rollout_conditions: int = 60  # pool conditions run under the HMPC itself (0: skip the stage)
    rollout_duration_s: float = 3.0  # 0 .. 3 s: the start-up transient and the disturbance at 2 s
    rollout_stride: int = 3
    rollout_initial_state: str = (
        "reference"  # start on the reference, as the paper's conditions do ("home": from zeros)
    )
    dagger_rounds: int = 0  # the shipped bundles: 0 (docs/lmpc.md); --dagger-rounds N
    dagger_conditions: int = 16  # pool conditions (after the rollout ones) run under the intermediate LMPC
    dagger_duration_s: float = 3.0
    dagger_states_per_law: int = 4000
    augment_repeat: int = 2  # base repeat of the on-policy (rollout, DAgger) samples in training
    augment_epochs: int = 100
    deploy_hidden: tuple[int, ...] = (128, 128)
    feature_set: str = "ref"  # hil_runtime.bundle.FEATURE_SETS; "ref" = (q_d, qd_d, qdd_d), docs/lmpc.md
    deploy_use_d_sample: bool = False  # also train the deployed emulator on D_sample (feedback-only states)
    on_policy_max_error_rad: float = 0.0175  # on-policy samples kept where every |e_j| is below this (1 deg)
    residual_percentile: float = 100.0  # trust region: per-joint bound on |tau_L - tau_fb|
    box_margin: float = (
        0.5  # trust region: alpha fades from 1 at the box edge to 0 at this fraction of its range outside
    )
    # per law, the trust region (box, margin) is chosen among these by closed-loop runs on pool
    # conditions (never the paper's); box "on_policy": the on-policy training states, "labeled": those
    # and every HMPC-labeled D_sample state (feedback-only states with errors of degrees)
    trust_candidates: tuple[tuple[str, float], ...] = (
        ("on_policy", 0.5),
        ("on_policy", 32.0),
        ("on_policy", 256.0),
        ("labeled", 0.1),
    )
    selection_conditions: int = 6  # pool conditions after the rollout and DAgger ones
    selection_duration_s: float = 3.0
    workers: int | None = None  # processes; None = one per CPU
    executor: str = DEFAULT_EXECUTOR  # models.executors.EXECUTORS: serial, local, ray

    @property
    def laws(self) -> tuple[str, ...]:
        return self.dataset.laws


def _progress(progress: Progress | None, label: str, total: int) -> Callable[[int], None]:
    return progress(label, total) if progress is not None else (lambda n: None)


# --- stage 1 ----------------------------------------------------------------------------------
def stage_dataset(
    config: PipelineConfig, work: Path, executor: Executor, progress: Progress | None = None, force: bool = False
) -> Path:
    path = work / "raw.h5"
    if path.exists() and not force:
        raw = load_raw_dataset(path)  # a corrupt file is an error here, never silently regenerated over
        if raw.manifest.get("spec") != json.loads(json.dumps(asdict(config.dataset))):
            raise ModelInputError(
                f"dataset {path}: made with other settings than asked ({raw.manifest.get('spec')}); "
                "use --force-dataset to regenerate it"
            )
        return path
    return generate_raw_dataset(
        config.dataset, path, executor, _progress(progress, "dataset: simulate chunks", config.dataset.chunks)
    )


# --- stage 2 ----------------------------------------------------------------------------------
def choose_samples(raw: RawLaw, config: PipelineConfig, budget: int, seed: int) -> dict[str, Any]:
    """Optimal, uniform and test indices for one law, with the Theorem 2 quantities used."""
    rng = np.random.default_rng(seed)
    pool = np.flatnonzero(raw.run < config.pool_conditions)
    held = np.flatnonzero(raw.run >= config.pool_conditions)
    if held.size < config.test_per_law:
        raise ModelInputError(f"pipeline: {held.size} held-out samples, test_per_law {config.test_per_law}")
    t_pool = raw.t_s[pool]
    proportions = time_proportions(t_pool)
    tolerances = np.array([r.tolerance for r in PAPER_REGIONS])
    estimated = estimate_lipschitz_delta(t_pool, raw.run[pool], raw.features()[pool], raw.tau_fb[pool])
    ldelta = estimated if config.lipschitz_delta == "estimate" else np.asarray(config.lipschitz_delta, float)
    weights = optimal_weights(tolerances, proportions, ldelta, config.epsilon, config.power)
    return {
        "optimal": pool[optimal_sample(t_pool, budget, weights, rng)],
        "uniform": pool[uniform_sample(pool.size, budget, rng)],
        "test": np.sort(rng.choice(held, size=config.test_per_law, replace=False)),
        "theorem2": {
            "proportions": proportions.tolist(),
            "tolerances": tolerances.tolist(),
            "lipschitz_delta_used": np.asarray(ldelta).tolist(),
            "lipschitz_delta_estimated": estimated.tolist(),
            "weights": weights.tolist(),
            "epsilon": config.epsilon,
            "power": config.power,
        },
    }


def stage_label(
    config: PipelineConfig,
    work: Path,
    labeler: Labeler | None = None,
    progress: Progress | None = None,
    executor: Executor | None = None,
) -> Path:
    """Sample every law and label the union of its optimal, uniform and test states."""
    raw_path = work / "raw.h5"
    raw = load_raw_dataset(raw_path)
    robot = load_robot(config.dataset.robot)
    labeler = labeler or hmpc_labeler
    per_law = config.budget // len(config.laws)
    chosen = {law: choose_samples(raw.laws[law], config, per_law, seed=1000 + i) for i, law in enumerate(config.laws)}
    unions = {law: np.unique(np.concatenate([c["optimal"], c["uniform"], c["test"]])) for law, c in chosen.items()}
    advance = _progress(progress, "label: HMPC on sampled states", sum(u.size for u in unions.values()))
    out = work / "labels.h5"
    started = time.perf_counter()
    wall: dict[str, float] = {}
    with write_h5(out) as h5:
        for law_name in config.laws:
            law = make_law(law_name, robot, config.dataset.period_s, config.dataset.gain_set)
            rows, index = raw.laws[law_name], unions[law_name]
            taus, statuses = [], []
            law_start = time.perf_counter()
            for lo in range(0, index.size, config.label_chunk):
                part = rows.take(index[lo : lo + config.label_chunk])
                tau, status = labeler(law, robot, part, executor)
                taus.append(np.asarray(tau, float))
                statuses.append(np.asarray(status, np.int32))
                advance(len(part))
            wall[law_name] = time.perf_counter() - law_start
            group = h5.create_group(law_name)
            group.create_dataset("index", data=index)
            group.create_dataset("tau_star", data=np.concatenate(taus))
            group.create_dataset("status", data=np.concatenate(statuses))
            for key in ("optimal", "uniform", "test"):
                group.create_dataset(key, data=chosen[law_name][key])
            group.attrs["theorem2"] = json.dumps(chosen[law_name]["theorem2"])
        write_manifest(
            h5,
            {
                "schema": LABELS_SCHEMA,
                "raw": str(raw_path),
                "raw_manifest_created": raw.manifest.get("created"),
                "git_commit": git_commit(),
                "labeler": getattr(labeler, "__name__", repr(labeler)),
                "hmpc_options": LABEL_HMPC_OPTIONS if labeler is hmpc_labeler else None,
                "budget": config.budget,
                "per_law": per_law,
                "wall_s": round(time.perf_counter() - started, 1),
                "wall_s_per_law": wall,
                "config": _config_json(config),
            },
        )
    return out


@dataclass
class LawLabels:
    index: np.ndarray
    tau_star: np.ndarray
    status: np.ndarray
    sets: dict[str, np.ndarray] = field(default_factory=dict)
    theorem2: dict[str, Any] = field(default_factory=dict)

    def targets(self, raw_index: np.ndarray) -> np.ndarray:
        return self.tau_star[np.searchsorted(self.index, raw_index)]


def load_labels(path: Path) -> tuple[dict[str, Any], dict[str, LawLabels]]:
    out = {}
    with read_h5(path, "labels", LABELS_SCHEMA, missing="no such file (run the label stage first)") as (h5, manifest):
        for law in h5:
            g = h5[law]
            out[law] = LawLabels(
                g["index"][...],
                g["tau_star"][...],
                g["status"][...],
                {k: g[k][...] for k in ("optimal", "uniform", "test")},
                json.loads(g.attrs["theorem2"]),
            )
    return manifest, out


# --- stage 3 ----------------------------------------------------------------------------------
def _train_task(task: tuple) -> dict[str, Any]:
    """Worker: one (law, strategy, seed) training; returns the weights and the curves."""
    law, strategy, seed, x, y, x_test, y_test, region_test, norm, train_config = task
    from models.lmpc.emulator import evaluate_mse

    result = train_emulator(x, y, replace(train_config, seed=seed), normalization=norm)
    test = {"all": evaluate_mse(result.emulator, x_test, y_test)}
    for i, region in enumerate(PAPER_REGIONS):
        mask = region_test == i
        test[region.name] = evaluate_mse(result.emulator, x_test[mask], y_test[mask])
    return {
        "law": law,
        "strategy": strategy,
        "seed": seed,
        "summary": result.summary(),
        "train_mse": result.train_mse,
        "val_mse": result.val_mse,
        "test_mse": test,
        "state_dict": {k: v.numpy() for k, v in result.emulator.state_dict().items()},
    }


def stage_train(
    config: PipelineConfig, work: Path, executor: Executor, progress: Progress | None = None
) -> dict[str, Any]:
    raw = load_raw_dataset(work / "raw.h5", config.laws)
    _, labels = load_labels(work / "labels.h5")
    tasks = []
    for law in config.laws:
        rows, lab = raw.laws[law], labels[law]
        x_all = rows.features()
        norm_idx = lab.sets["uniform"]  # one normalization per law, shared by every run compared
        norm = (x_all[norm_idx], lab.targets(norm_idx))
        x_test, y_test = x_all[lab.sets["test"]], lab.targets(lab.sets["test"])
        region_test = region_index(rows.t_s[lab.sets["test"]])
        for strategy in ("optimal", "uniform"):
            idx = lab.sets[strategy]
            for seed in config.seeds:
                tasks.append(
                    (law, strategy, seed, x_all[idx], lab.targets(idx), x_test, y_test, region_test, norm, config.train)
                )
    advance = _progress(progress, "train: emulators (law x sampling x seed)", len(tasks))
    runs = []
    for result in executor.map(_train_task, tasks):
        runs.append(result)
        advance(1)
    return {
        "runs": runs,
        "labels_theorem2": {law: labels[law].theorem2 for law in config.laws},
        "label_status": {law: np.bincount(labels[law].status, minlength=4).tolist() for law in config.laws},
    }


def summarize_training(trained: dict[str, Any], laws: tuple[str, ...]) -> dict[str, Any]:
    """Mean over seeds of the final (best-epoch) validation MSE and the test MSE, per law and strategy."""
    table: dict[str, Any] = {}
    for law in laws:
        row = {}
        for strategy in ("optimal", "uniform"):
            runs = [r for r in trained["runs"] if r["law"] == law and r["strategy"] == strategy]
            row[strategy] = {
                "val_mse_mean": float(np.mean([r["summary"]["best_val_mse_normalized"] for r in runs])),
                "test_mse_mean": float(np.mean([r["test_mse"]["all"] for r in runs])),
                "test_mse_by_region": {
                    k: float(np.mean([r["test_mse"][k] for r in runs])) for k in runs[0]["test_mse"] if k != "all"
                },
                "val_rmse_nm_mean": np.mean([r["summary"]["val_rmse_nm"] for r in runs], 0).tolist(),
                "seeds": [r["seed"] for r in runs],
            }
        for key in ("val_mse_mean", "test_mse_mean"):
            row[f"{key}_optimal_over_uniform"] = row["optimal"][key] / row["uniform"][key]
        table[law] = row
    overall = {
        key: float(np.mean([table[law][f"{key}_optimal_over_uniform"] for law in laws]))
        for key in ("val_mse_mean", "test_mse_mean")
    }
    return {"per_law": table, "mean_ratio_optimal_over_uniform": overall}


def plot_sampling_curves(trained: dict[str, Any], laws: tuple[str, ...], path: Path) -> None:
    """Validation MSE per epoch, optimal vs uniform (mean and range over seeds), one panel per law."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = 3
    fig, axes = plt.subplots((len(laws) + cols - 1) // cols, cols, figsize=(12, 6.5), squeeze=False)
    for ax, law in zip(axes.flat, laws, strict=False):
        for strategy, color in (("optimal", "tab:red"), ("uniform", "tab:blue")):
            curves = [r["val_mse"] for r in trained["runs"] if r["law"] == law and r["strategy"] == strategy]
            length = max(len(c) for c in curves)
            padded = np.array([c + [c[-1]] * (length - len(c)) for c in curves])
            epochs = np.arange(1, length + 1)
            ax.semilogy(epochs, padded.mean(0), color=color, label=f"{strategy} (mean of {len(curves)})")
            ax.fill_between(epochs, padded.min(0), padded.max(0), color=color, alpha=0.2)
        ax.set_title(law.upper())
        ax.set_xlabel("epoch")
        ax.set_ylabel("validation MSE (normalized)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Emulator training: Theorem 2 (optimal) vs uniform sampling, same budget")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --- stage 3b (beyond the paper) -------------------------------------------------------------------
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
    from hil_runtime.bundle import emulator_features

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
    advance = _progress(progress, "augment: HMPC rollouts, DAgger rounds, training", steps)
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
            _export_deployed(config, robot, law, r, out / robot.name / law, {"stage": "intermediate (DAgger)"}, {})

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
            _export_deployed(
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


def _export_deployed(
    config: PipelineConfig,
    robot: Any,
    law_name: str,
    result: dict[str, Any],
    out: Path,
    training: dict[str, Any],
    validation: dict[str, Any],
    parity_inputs: np.ndarray | None = None,
) -> dict[str, Any]:
    import torch

    from models.lmpc.bundle_export import export_bundle
    from models.lmpc.emulator import Emulator

    spec = config.dataset
    if "box_margin" in result:  # chosen per law by select_margins
        config = replace(config, box_margin=result["box_margin"])
    width = len(FEATURE_SETS[config.feature_set]) * robot.n_joints
    emulator = Emulator(width, robot.n_joints, config.deploy_hidden)
    emulator.load_state_dict({k: torch.as_tensor(v) for k, v in result["state_dict"].items()})
    training = {
        "gain_set": spec.gain_set,
        **training,
        "trust": {
            "residual_percentile": config.residual_percentile,
            "box": result.get("box_kind", "on_policy"),
            "box_margin": config.box_margin,
            "box_note": "on_policy: min/max of the guard features over the on-policy training states; labeled: "
            "those and the HMPC-labeled D_sample states; chosen per law (augment stage, docs/lmpc.md)",
        },
    }
    return export_bundle(
        out,
        make_law(law_name, robot, spec.period_s, spec.gain_set),
        robot,
        emulator,
        training,
        validation,
        trust_region=result["box"],
        parity_inputs=parity_inputs,
        residual=True,
        residual_bound_nm=result["residual_bound_nm"],
        box_margin=config.box_margin,
        feature_set=config.feature_set,
    )


# --- stage 4 ----------------------------------------------------------------------------------
def stage_export(
    config: PipelineConfig,
    work: Path,
    trained: dict[str, Any],
    bundles: Path,
    strategy: str = "optimal",
    seed: int | None = None,
) -> dict[str, Any]:
    import torch

    from models.lmpc.bundle_export import export_bundle
    from models.lmpc.emulator import Emulator

    robot = load_robot(config.dataset.robot)
    raw = load_raw_dataset(work / "raw.h5", config.laws)
    labels_manifest, labels = load_labels(work / "labels.h5")
    seed = config.seeds[0] if seed is None else seed
    augmented = None
    if (work / "augmented.pkl").is_file() and config.rollout_conditions > 0:
        import pickle

        with open(work / "augmented.pkl", "rb") as handle:
            augmented = pickle.load(handle)
    out = {}
    for law_name in config.laws:
        run = next(
            r for r in trained["runs"] if r["law"] == law_name and r["strategy"] == strategy and r["seed"] == seed
        )
        if augmented is not None:
            run = {
                **run,
                "state_dict": augmented[law_name]["state_dict"],
                "augmented_summary": augmented[law_name]["summary"],
            }
        law = make_law(law_name, robot, config.dataset.period_s, config.dataset.gain_set)
        rows, lab = raw.laws[law_name], labels[law_name]
        x_train = rows.features(GUARD_FEATURES)[lab.sets[strategy]]  # the trust box is over the guard features
        parity = rows.take(lab.sets["test"][:256])
        parity_x = np.concatenate([parity.q, parity.qd, parity.q_d, parity.qd_d, parity.qdd_d, parity.law_state], 1)
        training = {
            "dataset": {
                "file": "raw.h5",
                "spec": raw.manifest["spec"],
                "git_commit": raw.manifest["git_commit"],
                "created": raw.manifest["created"],
            },
            "labels": {
                "labeler": labels_manifest["labeler"],
                "hmpc_options": labels_manifest["hmpc_options"],
                "status_counts": np.bincount(lab.status, minlength=4).tolist(),
            },
            "sampling": {"strategy": strategy, "samples": int(lab.sets[strategy].size), "theorem2": lab.theorem2},
            "emulator": run.get("augmented_summary", run["summary"]),
            "augmentation": None
            if augmented is None
            else {
                "hmpc_rollout_conditions": config.rollout_conditions,
                "rollout_duration_s": config.rollout_duration_s,
                "dagger_rounds": config.dagger_rounds,
                "dagger_conditions": config.dagger_conditions,
                "repeat": config.augment_repeat,
                "samples": augmented[law_name].get("samples"),
                "feature_set": config.feature_set,
                "note": "D_sample (Theorem 2) + HMPC closed-loop states + DAgger rounds, residual target "
                "tau* - tau_fb, Theorem 2 region weights on the on-policy samples; docs/lmpc.md",
            },
            "seed": seed,
            "gain_set": config.dataset.gain_set,
            "git_commit": git_commit(),
        }
        validation = {
            "val_mse_normalized": run["summary"]["best_val_mse_normalized"],
            "val_rmse_nm": run["summary"]["val_rmse_nm"],
            "test_mse_normalized": run["test_mse"],
            "test_set": "uniform over held-out conditions",
        }
        if augmented is not None:
            validation["note"] = (
                "val/test MSE above: the paper-recipe emulator of the train stage; the deployed one's "
                "validation is training.emulator (residual target, normalized by its RMS)"
            )
            manifest = _export_deployed(
                config,
                robot,
                law_name,
                augmented[law_name],
                bundles / robot.name / law_name,
                {k: v for k, v in training.items() if k != "gain_set"},
                validation,
                parity_x,
            )
        else:
            emulator = Emulator(5 * robot.n_joints, robot.n_joints, config.train.hidden)
            emulator.load_state_dict({k: torch.as_tensor(v) for k, v in run["state_dict"].items()})
            manifest = export_bundle(
                bundles / robot.name / law_name,
                law,
                robot,
                emulator,
                training,
                validation,
                trust_region=(x_train.min(0), x_train.max(0)),
                parity_inputs=parity_x,
                box_margin=config.box_margin,
            )
        out[law_name] = {
            "path": str(bundles / robot.name / law_name),
            "onnx_vs_torch_max_abs_nm": manifest["validation"]["onnx_vs_torch_max_abs_nm"],
        }
    return out


def _config_json(config: PipelineConfig) -> dict[str, Any]:
    return json.loads(json.dumps(asdict(config), default=str))


def run_pipeline(
    config: PipelineConfig,
    work: Path,
    bundles: Path,
    stages: tuple[str, ...] = ("dataset", "label", "train", "augment", "export"),
    executor: Executor | None = None,
    labeler: Labeler | None = None,
    progress: Progress | None = None,
    force_dataset: bool = False,
) -> dict[str, Any]:
    """Run the stages on ``executor`` (default: ``config.executor`` with ``config.workers``, closed
    at the end); write <work>/pipeline.json (timings, Theorem 2 weights, training figures)."""
    work.mkdir(parents=True, exist_ok=True)
    if executor is None:
        with make_executor(config.executor, config.workers) as owned:
            return run_pipeline(config, work, bundles, stages, owned, labeler, progress, force_dataset)
    summary_path = work / "pipeline.json"
    summary: dict[str, Any] = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    summary.setdefault("wall_s", {})
    if "dataset" in stages:
        started = time.perf_counter()
        stage_dataset(config, work, executor, progress, force=force_dataset)
        summary["wall_s"]["dataset"] = round(time.perf_counter() - started, 1)
    if "label" in stages:
        started = time.perf_counter()
        stage_label(config, work, labeler, progress, executor)
        summary["wall_s"]["label"] = round(time.perf_counter() - started, 1)
    trained = None
    if "train" in stages:
        started = time.perf_counter()
        trained = stage_train(config, work, executor, progress)
        summary["wall_s"]["train"] = round(time.perf_counter() - started, 1)
        summary["training"] = summarize_training(trained, config.laws)
        summary["theorem2"] = trained["labels_theorem2"]
        summary["label_status"] = trained["label_status"]
        plot_sampling_curves(trained, config.laws, work / "sampling_curves.png")
        curves = [
            {k: r[k] for k in ("law", "strategy", "seed", "summary", "train_mse", "val_mse", "test_mse")}
            for r in trained["runs"]
        ]
        (work / "training.json").write_text(json.dumps(curves))
        import pickle

        with open(work / "trained.pkl", "wb") as handle:
            pickle.dump(trained, handle)
    if "augment" in stages and config.rollout_conditions > 0:
        started = time.perf_counter()
        summary["augment"] = stage_augment(config, work, executor, progress)
        summary["wall_s"]["augment"] = round(time.perf_counter() - started, 1)
    if "export" in stages:
        started = time.perf_counter()
        if trained is None:
            import pickle

            if not (work / "trained.pkl").is_file():
                raise ModelInputError(f"pipeline: {work / 'trained.pkl'} missing (run the train stage first)")
            with open(work / "trained.pkl", "rb") as handle:
                trained = pickle.load(handle)
        summary["bundles"] = stage_export(config, work, trained, bundles)
        summary["wall_s"]["export"] = round(time.perf_counter() - started, 1)
    summary["wall_s"]["total"] = round(sum(v for k, v in summary["wall_s"].items() if k != "total"), 1)
    summary["config"] = _config_json(config)
    summary["git_commit"] = git_commit()
    summary_path.write_text(json.dumps(summary, indent=2))
    return summary
