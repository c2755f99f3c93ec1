"""Per-joint tracking error and torque figures from a telemetry record (like the paper's Fig. 5).

Reads what ``hil telemetry record`` writes, and also ``hil run --record`` files (same column
names: q, q_ref, tau, tau_fb, t_s). matplotlib is imported here only, with a one-line error when
it is absent (it comes with the ``models`` extra; the runtime itself never needs it).
"""

from __future__ import annotations

import math
import os
import stat
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

# Limits checked before anything is decompressed: a 6 MB npz can inflate to 6 GiB (issue 20), and
# a figure of hundreds of panels takes minutes to draw. A 1 kHz record of 6 joints is ~330 B a
# sample: 1 GiB holds about 50 minutes of it.
MAX_RECORD_BYTES = 1 << 30  # all arrays together, uncompressed
MAX_ARRAYS = 64
MAX_JOINTS = 32  # one panel per joint
SAMPLE_COLUMNS = ("q", "q_ref", "tau")  # required, (samples, joints)
OPTIONAL_COLUMNS = ("tau_fb", "t_s", "seq")  # checked against the required ones when present


class PlotError(ValueError):
    """A record that cannot be plotted, or matplotlib missing; one line, exit code 2."""

    exit_code = 2


def _check_regular(path: Path) -> None:
    try:
        mode = os.stat(path).st_mode  # stat, not open: a FIFO would block the open
    except FileNotFoundError:
        raise PlotError(f"{path}: no such file") from None
    except OSError as exc:
        raise PlotError(f"{path}: cannot read it ({exc.strerror})") from None
    if not stat.S_ISREG(mode):
        raise PlotError(f"{path}: not a regular file (a FIFO, device or directory is never read)")


def _check_archive(path: Path) -> None:
    """A zip of at most MAX_ARRAYS .npy members whose headers promise no more than
    MAX_RECORD_BYTES together (read from the headers, before any array is inflated)."""
    try:
        with zipfile.ZipFile(path) as archive:
            members = archive.infolist()
            if len(members) > MAX_ARRAYS:
                raise PlotError(f"{path}: {len(members)} arrays (a record has at most {MAX_ARRAYS})")
            total = 0
            for member in members:
                total += member.file_size  # zipfile never inflates a member past its declared size
                with archive.open(member) as handle:
                    version = np.lib.format.read_magic(handle)
                    read_header = (
                        np.lib.format.read_array_header_1_0
                        if version == (1, 0)
                        else np.lib.format.read_array_header_2_0
                    )
                    shape, _, dtype = read_header(handle)
                nbytes = math.prod(shape) * dtype.itemsize
                if nbytes > member.file_size:
                    raise PlotError(
                        f"{path}: array {member.filename!r} claims {nbytes} bytes, holds {member.file_size}"
                    )
            if total > MAX_RECORD_BYTES:
                raise PlotError(
                    f"{path}: {total / 2**20:.0f} MiB uncompressed (limit {MAX_RECORD_BYTES >> 20} MiB): "
                    "plot a shorter record"
                )
    except PlotError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError, ValueError, KeyError, TypeError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PlotError(f"{path}: not a telemetry record ({reason})") from None


def load_record(path: Path) -> dict[str, Any]:
    _check_regular(path)
    if path.suffix.lower() == ".mcap":  # hil run / hil telemetry record --out x.mcap (docs/formats.md)
        from hil_runtime.formats.mcap_record import McapRecordError, read_mcap_record

        try:
            return _checked(path, read_mcap_record(path))
        except McapRecordError as exc:
            raise PlotError(str(exc)) from None
    _check_archive(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            record = {name: data[name] for name in data.files}
    except FileNotFoundError:
        raise PlotError(f"{path}: no such file") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PlotError(f"{path}: not a telemetry record ({reason})") from None
    return _checked(path, record)


def _checked(path: Path, record: dict[str, Any]) -> dict[str, Any]:
    """The columns the figures read, consistent with one another (one line naming the field if not)."""
    shape = None
    for name in SAMPLE_COLUMNS:
        if name not in record:
            raise PlotError(f"{path}: not a telemetry record (no {name!r} column)")
        column = record[name] = np.asarray(record[name])
        if column.ndim != 2:
            raise PlotError(f"{path}: column {name!r} is not (samples, joints)")
        if column.dtype.kind not in "fiu":
            raise PlotError(f"{path}: column {name!r} holds {column.dtype}, not numbers")
        if shape is not None and column.shape != shape:
            raise PlotError(f"{path}: column {name!r} has shape {column.shape}, 'q' {shape}")
        shape = column.shape
    assert shape is not None
    for name in OPTIONAL_COLUMNS:
        if name in record:
            column = record[name] = np.asarray(record[name])
            expected = shape if name == "tau_fb" else shape[:1]
            if column.shape != expected or column.dtype.kind not in "fiu":
                raise PlotError(f"{path}: column {name!r} has shape {column.shape} {column.dtype}, expected {expected}")
    if shape[0] == 0:
        raise PlotError(f"{path}: the record holds no samples")
    if shape[1] > MAX_JOINTS:
        raise PlotError(f"{path}: column 'q': {shape[1]} joints (plot draws at most {MAX_JOINTS})")
    if "period_s" in record:
        period = record["period_s"] = np.asarray(record["period_s"])
        if period.shape != () or period.dtype.kind not in "fiu" or not 0.0 < float(period) < math.inf:
            raise PlotError(f"{path}: field period_s: {period.tolist()!r} is not a positive number of seconds")
    if "joints" in record and (np.ndim(record["joints"]) != 1 or np.asarray(record["joints"]).dtype.kind not in "US"):
        raise PlotError(f"{path}: field joints: not a list of names")
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
    names = [str(name)[:40] for name in record.get("joints", [])]  # a label, not a document
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
        figure.suptitle(f"{title} ({path.name})", fontsize=10, parse_math=False)
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
        ax.set_ylabel(f"{names[j]}\n[rad]", fontsize=8, parse_math=False)  # names are data, not mathtext
        ax.text(0.99, 0.9, f"RMS {rms:.2e} rad", transform=ax.transAxes, ha="right", va="top", fontsize=7)

    def torque(j: int, ax: Any) -> None:
        ax.plot(t_s, record["tau"][:, j], lw=0.8, color="C1", label="tau (applied)")
        if "tau_fb" in record and record["tau_fb"].shape == record["tau"].shape:
            ax.plot(t_s, record["tau_fb"][:, j], lw=0.6, color="C2", alpha=0.7, label="tau_fb (law)")
        ax.set_ylabel(f"{names[j]}\n[N m]", fontsize=8, parse_math=False)
        if j == 0:
            ax.legend(fontsize=7, loc="upper right")

    written = [
        per_joint_figure("tracking error q_ref - q", "tracking_error", tracking_error),
        per_joint_figure("joint torque", "torque", torque),
    ]
    return written
