"""Stage ``train``: the paper's emulators, Theorem 2 (optimal) vs uniform sampling, seeds in parallel;
the summary table and the sampling curves."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from models.executors import Executor
from models.lmpc.dataset import load_raw_dataset
from models.lmpc.emulator import train_emulator
from models.lmpc.pipeline.config import PipelineConfig, Progress, progress_callback
from models.lmpc.pipeline.labeling import load_labels
from models.lmpc.sampling import (
    PAPER_REGIONS,
    region_index,
)


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
    advance = progress_callback(progress, "train: emulators (law x sampling x seed)", len(tasks))
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
