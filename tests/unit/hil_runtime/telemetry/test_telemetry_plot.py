"""``hil telemetry plot``: PNGs from a record (ours or ``hil run --record``'s), clear refusals."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from hil_runtime.telemetry.plot import PlotError, load_record, plot_record


def _write(path: Path, samples: int = 200, n_joints: int = 3, **extra: object) -> Path:
    t_s = np.arange(samples) * 1e-3
    q = np.sin(t_s[:, None] + np.arange(n_joints))
    # numpy's stub types savez's **kwds as also reaching its bool allow_pickle:
    np.savez(path, t_s=t_s, q=q, q_ref=q + 0.01, tau=q * 2, tau_fb=q * 1.5, **extra)  # type: ignore[arg-type]
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
