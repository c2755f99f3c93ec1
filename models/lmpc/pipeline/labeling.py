"""Data collection and labeling: D_input (stage ``dataset``), Theorem 2 sampling and the HMPC labels of
the sampled states (stage ``label``, <work>/labels.h5), and their reader."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from models.errors import ModelInputError
from models.executors import Executor
from models.feedback import make_law
from models.lmpc.dataset import RawLaw, generate_raw_dataset, git_commit, load_raw_dataset
from models.lmpc.h5file import read_h5, write_h5, write_manifest
from models.lmpc.labels import LABEL_HMPC_OPTIONS, Labeler, hmpc_labeler
from models.lmpc.pipeline.config import PipelineConfig, Progress, config_json, progress_callback
from models.lmpc.sampling import (
    PAPER_REGIONS,
    estimate_lipschitz_delta,
    optimal_sample,
    optimal_weights,
    time_proportions,
    uniform_sample,
)
from models.robots import load_robot

LABELS_SCHEMA = "hil-lmpc-labels/1"


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
        config.dataset, path, executor, progress_callback(progress, "dataset: simulate chunks", config.dataset.chunks)
    )


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
    advance = progress_callback(progress, "label: HMPC on sampled states", sum(u.size for u in unions.values()))
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
                "config": config_json(config),
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
