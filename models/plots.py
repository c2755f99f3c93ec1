"""Plots people would rather look at than read: per-joint tracking errors (the paper's Fig. 5)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from hil_runtime.outputs import atomic_path

_STYLE = {"fb": "-", "hmpc": "--", "lmpc": ":"}


def save_figure(fig: Any, path: Path) -> Path:
    """Write ``fig`` as a PNG (a complete file or none, even on Ctrl-C) and close it."""
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return path


def plot_tracking_errors(
    trajectories: dict[tuple[str, str, str], dict[str, np.ndarray]],
    laws: tuple[str, ...],
    modes: tuple[str, ...],
    conditions: list[str],
    out_dir: Path,
) -> list[Path]:
    """One PNG per (law, condition): tracking error (deg) per joint, one line per mode; plus one
    PNG per condition with the joint-averaged error of every law and mode."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for cond in conditions:
        for law in laws:
            fig, axes = plt.subplots(3, 2, figsize=(10, 7), sharex=True)
            for mode in modes:
                run = trajectories.get((law, mode, cond))
                if run is None:
                    continue
                err = np.degrees(run["q_ref"] - run["q"])
                for j, ax in enumerate(axes.flat[: err.shape[1]]):
                    ax.plot(run["t"], err[:, j], _STYLE.get(mode, "-"), lw=1, label=mode.upper())
                    ax.set_title(f"joint {j + 1}", fontsize=9)
                    ax.grid(alpha=0.3)
            for ax in axes[-1]:
                ax.set_xlabel("t (s)")
            for ax in axes[:, 0]:
                ax.set_ylabel("e (deg)")
            axes.flat[0].legend(fontsize=8)
            fig.suptitle(f"{law.upper()} tracking error, condition {cond}")
            fig.tight_layout()
            path = out_dir / f"{law}_{cond}.png"
            written.append(save_figure(fig, path))

        fig, ax = plt.subplots(figsize=(9, 4.5))
        for i, law in enumerate(laws):
            for mode in modes:
                run = trajectories.get((law, mode, cond))
                if run is None:
                    continue
                mean_abs = np.abs(np.degrees(run["q_ref"] - run["q"])).mean(axis=1)
                ax.plot(
                    run["t"],
                    mean_abs,
                    _STYLE.get(mode, "-"),
                    color=f"C{i}",
                    lw=1,
                    label=f"{law.upper()} {mode.upper()}",
                )
        ax.set_yscale("log")
        ax.set_ylim(bottom=1e-3)
        ax.set_xlabel("t (s)")
        ax.set_ylabel("mean |e| over joints (deg)")
        ax.set_title(f"Average joint tracking error, condition {cond}")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, ncol=3)
        fig.tight_layout()
        path = out_dir / f"average_error_{cond}.png"
        written.append(save_figure(fig, path))
    return written
