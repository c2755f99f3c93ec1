"""``hil telemetry plot``: PNGs from a record (ours or ``hil run --record``'s), clear refusals."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil_runtime.telemetry.plot import PlotError, load_record, plot_record
from tests.unit.hil_runtime.telemetry import npz_files


def _write(path: Path, samples: int = 200, n_joints: int = 3, **extra: Any) -> Path:
    t_s = np.arange(samples) * 1e-3
    q = np.sin(t_s[:, None] + np.arange(n_joints))
    # extra: Any, as numpy's stub types savez's **kwds as also reaching its bool allow_pickle
    np.savez(path, t_s=t_s, q=q, q_ref=q + 0.01, tau=q * 2, tau_fb=q * 1.5, **extra)
    return path


def test_plot_writes_two_pngs(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    record = _write(tmp_path / "run.npz", n_joints=3, joints=np.asarray(["a", "b", "c"]))
    written = plot_record(record, tmp_path / "figs")
    assert [p.name for p in written] == ["run_tracking_error.png", "run_torque.png"]
    for path in written:
        assert path.read_bytes()[:4] == b"\x89PNG"
    assert not list((tmp_path / "figs").glob(".*partial*"))


def test_refusals(tmp_path: Path) -> None:
    with pytest.raises(PlotError, match="nope.npz: no such file"):
        load_record(tmp_path / "nope.npz")
    (tmp_path / "text.npz").write_text("not numpy")
    with pytest.raises(PlotError, match="text.npz: not a telemetry record"):
        load_record(tmp_path / "text.npz")
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(PlotError, match="other.npz: not a telemetry record \\(no 'q' column\\)"):
        load_record(tmp_path / "other.npz")
    empty = _write(tmp_path / "empty.npz", samples=0)
    with pytest.raises(PlotError, match="the record holds no samples"):
        load_record(empty)


def test_missing_matplotlib_is_one_clear_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    with pytest.raises(PlotError) as info:
        plot_record(_write(tmp_path / "run.npz"))
    assert str(info.value) == (
        "hil telemetry plot needs matplotlib: pip install 'hil-runtime[models]' (or pip install matplotlib)"
    )
    assert info.value.exit_code == 2


def test_time_axis_is_cycles_times_period_when_known() -> None:
    from hil_runtime.telemetry.plot import _time_axis

    q = np.zeros((3, 2))
    record = {
        "q": q,
        "seq": np.array([10, 11, 13], dtype=np.uint64),
        "period_s": np.asarray(0.001),
        "t_s": np.array([0.0, 0.5, 0.9]),
    }
    t_s, label = _time_axis(record)
    np.testing.assert_allclose(t_s, [0.0, 0.001, 0.003])
    assert label == "time [s] (cycles x period)"
    del record["period_s"]
    t_s, label = _time_axis(record)
    np.testing.assert_allclose(t_s, [0.0, 0.5, 0.9])
    assert label == "time [s]"


# --- issue 20: hostile or broken records -------------------------------------------------------------


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (npz_files.truncated, "not a telemetry record ("),
        (npz_files.mismatched, "column 'q_ref' has shape (60, 3), 'q' (50, 3)"),
        (npz_files.period_string, "field period_s: 'fast' is not a positive number of seconds"),
        (npz_files.many_joints, "column 'q': 600 joints (plot draws at most 32)"),
        (lambda: npz_files.record(t_s=np.zeros(7)), "column 't_s' has shape (7,)"),
        (lambda: npz_files.record(q=np.full((50, 3), "x")), "column 'q' holds <U1, not numbers"),
        (lambda: npz_files.record(period_s=np.asarray(-1.0)), "field period_s: -1.0 is not a positive number"),
        (lambda: npz_files.record(joints=np.zeros((2, 2))), "field joints: not a list of names"),
    ],
)
def test_broken_records_are_one_line(tmp_path: Path, make: Callable[[], bytes], message: str) -> None:
    path = tmp_path / "bad.npz"
    path.write_bytes(make())
    with pytest.raises(PlotError) as info:
        load_record(path)
    text = str(info.value)
    assert text.startswith(f"{path}: ") and message in text and "\n" not in text, text


def test_an_inflating_record_is_refused_before_it_is_inflated(tmp_path: Path) -> None:
    import resource

    path = tmp_path / "bomb.npz"
    path.write_bytes(npz_files.inflating())
    assert path.stat().st_size < 2 << 20  # ~1 MB on disk, 1 GiB + 16 MiB inflated
    before_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(PlotError, match=r"bomb.npz: 1040 MiB uncompressed \(limit 1024 MiB\)"):
        load_record(path)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before_kb < 100_000  # nothing was inflated


def test_a_header_claiming_more_than_its_member_holds_is_refused(tmp_path: Path) -> None:
    good = npz_files.record()
    # q's .npy header says (50, 3); make it claim (5000000, 3) without the data to back it
    bad = good.replace(b"(50, 3)", b"(5000000, 3)".ljust(len(b"(50, 3)")), 1)
    assert bad != good
    path = tmp_path / "liar.npz"
    path.write_bytes(bad)
    with pytest.raises(PlotError, match="liar.npz: "):
        load_record(path)


def test_a_fifo_is_refused_without_blocking(tmp_path: Path) -> None:
    fifo = tmp_path / "run.npz"
    os.mkfifo(fifo)
    with pytest.raises(PlotError, match="run.npz: not a regular file"):
        load_record(fifo)  # opening it would block until a writer came


def test_joint_names_are_plain_text_not_mathtext(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    names = np.asarray(["$\\frac{", "a$b$c", "^_^{", "\\undefined$"])
    path = tmp_path / "run$x.npz"
    path.write_bytes(npz_files.record(n_joints=4, joints=names))
    written = plot_record(path, tmp_path / "figs")
    assert [p.read_bytes()[:4] for p in written] == [b"\x89PNG"] * 2
