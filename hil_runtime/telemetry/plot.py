"""Per-joint tracking error and torque figures from a telemetry record (like the paper's Fig. 5).

Reads what ``hil telemetry record`` writes, and also ``hil run --record`` files (same column
names: q, q_ref, tau, tau_fb, t_s). matplotlib is imported here only, with a one-line error when
it is absent (it comes with the ``models`` extra; the runtime itself never needs it).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


class PlotError(ValueError):
    """A record that cannot be plotted, or matplotlib missing; one line, exit code 2."""

    exit_code = 2


def load_record(path: Path) -> dict[str, Any]:
    if path.suffix.lower() == ".mcap":  # hil run / hil telemetry record --out x.mcap (docs/formats.md)
        from hil_runtime.formats.mcap_record import McapRecordError, read_mcap_record

        try:
            return read_mcap_record(path)
        except McapRecordError as exc:
            raise PlotError(str(exc)) from None
    try:
        with np.load(path, allow_pickle=False) as data:
            record = {name: data[name] for name in data.files}
    except FileNotFoundError:
        raise PlotError(f"{path}: no such file") from None
    except (OSError, ValueError) as exc:
        raise PlotError(f"{path}: not a telemetry record ({str(exc).splitlines()[0]})") from None
    for name in ("q", "q_ref", "tau"):
        if name not in record:
            raise PlotError(f"{path}: not a telemetry record (no {name!r} column)")
        if record[name].ndim != 2:
            raise PlotError(f"{path}: column {name!r} is not (samples, joints)")
    if len(record["q"]) == 0:
        raise PlotError(f"{path}: the record holds no samples")
    return record


def _time_axis(record: dict[str, Any]) -> tuple[np.ndarray, str]:
    """Cycle x period when both are known (a lock-stepped run is not wall time), else the record's t_s."""
    n = len(record["q"])
    if "seq" in record and "period_s" in record and record["period_s"].ndim == 0 and len(record["seq"]) == n:
        seq = record["seq"].astype(np.int64)
        return (seq - seq[0]) * float(record["period_s"]), "time [s] (cycles x period)"
    if "t_s" in record and len(record["t_s"]) == n:
        return np.asarray(record["t_s"], dtype=float), "time [s]"
    return np.arange(n, dtype=float), "sample"


def _joint_names(record: dict[str, Any]) -> list[str]:
    n = record["q"].shape[1]
    names = [str(name) for name in record.get("joints", [])]
    return names if len(names) == n else [f"joint {j + 1}" for j in range(n)]


def plot_record(path: Path, out_dir: Path | None = None) -> list[Path]:
    """Write ``<stem>_tracking_error.png`` and ``<stem>_torque.png``; returns their paths."""
    try:
        import matplotlib
    except ImportError:
        raise PlotError(
            "hil telemetry plot needs matplotlib: pip install 'hil-runtime[models]' (or pip install matplotlib)"
        ) from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hil_runtime.outputs import atomic_path, prepare_output_dir

    record = load_record(path)
    out = prepare_output_dir(out_dir if out_dir is not None else path.parent, option="--out-dir")
    t_s, t_label = _time_axis(record)
    names = _joint_names(record)
    n = len(names)
    error_rad = record["q_ref"] - record["q"]

    def per_joint_figure(title: str, suffix: str, draw: Any) -> Path:
        """One panel per joint (``draw(j, ax)``), a shared time axis, saved whole or not at all."""
        figure, axes = plt.subplots(n, 1, sharex=True, figsize=(8, 1.6 * n + 0.8), squeeze=False)
        for j, ax in enumerate(axes[:, 0]):
            draw(j, ax)
            ax.grid(alpha=0.3)
        axes[-1, 0].set_xlabel(t_label)
        figure.suptitle(f"{title} ({path.name})", fontsize=10)
        figure.tight_layout()
        target = out / f"{path.stem}_{suffix}.png"
        with atomic_path(target) as tmp:
            figure.savefig(tmp, dpi=110)
        plt.close(figure)
        return target

    def tracking_error(j: int, ax: Any) -> None:
        ax.plot(t_s, error_rad[:, j], lw=0.8, color="C0")
        ax.axhline(0.0, color="0.6", lw=0.5)
        rms = float(np.sqrt(np.mean(error_rad[:, j] ** 2)))
        ax.set_ylabel(f"{names[j]}\n[rad]", fontsize=8)
        ax.text(0.99, 0.9, f"RMS {rms:.2e} rad", transform=ax.transAxes, ha="right", va="top", fontsize=7)

    def torque(j: int, ax: Any) -> None:
        ax.plot(t_s, record["tau"][:, j], lw=0.8, color="C1", label="tau (applied)")
        if "tau_fb" in record and record["tau_fb"].shape == record["tau"].shape:
            ax.plot(t_s, record["tau_fb"][:, j], lw=0.6, color="C2", alpha=0.7, label="tau_fb (law)")
        ax.set_ylabel(f"{names[j]}\n[N m]", fontsize=8)
        if j == 0:
            ax.legend(fontsize=7, loc="upper right")

    written = [
        per_joint_figure("tracking error q_ref - q", "tracking_error", tracking_error),
        per_joint_figure("joint torque", "torque", torque),
    ]
    return written
