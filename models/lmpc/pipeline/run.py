"""``run_pipeline``: the stages in order on one executor, their wall times and figures in
<work>/pipeline.json."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from models.errors import ModelInputError
from models.executors import Executor, make_executor
from models.lmpc.dataset import git_commit
from models.lmpc.labels import Labeler
from models.lmpc.pipeline.augment import stage_augment
from models.lmpc.pipeline.config import PipelineConfig, Progress, config_json
from models.lmpc.pipeline.export import stage_export
from models.lmpc.pipeline.labeling import stage_dataset, stage_label
from models.lmpc.pipeline.training import plot_sampling_curves, stage_train, summarize_training


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
    summary["config"] = config_json(config)
    summary["git_commit"] = git_commit()
    summary_path.write_text(json.dumps(summary, indent=2))
    return summary
