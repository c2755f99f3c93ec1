"""hil demo's helpers (models/demo/analysis.py, processes.py, view.py): the record on the simulator's
grid, the comparison, the timing figures, the stale-directory sweep; the --gui mirror in DIRECT mode."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from models.demo import analysis
from models.lab.processes import OWNER_FILE, WORK_PREFIX, remove_stale_work_dirs


def _record(t_s: np.ndarray, n: int = 6) -> dict[str, np.ndarray]:
    rows = t_s.size
    q = np.outer(t_s, np.arange(1, n + 1))
    return {
        "t_s": t_s,
        "wall_s": t_s.copy(),
        "q": q,
        "qd": np.ones((rows, n)),
        "q_ref": q + 0.01,
        "qd_ref": np.ones((rows, n)),
        "tau": np.zeros((rows, n)),
        "tau_fb": np.zeros((rows, n)),
        "fallback": np.zeros(rows),
        "compute_s": np.full(rows, 1e-4),
        "exchange_s": np.full(rows, 5e-4),
    }


def test_lockstep_record_is_taken_row_for_row_and_cut_to_the_condition() -> None:
    record = _record(np.arange(120) * 1e-3)  # the daemon ran 20 cycles past the condition's end
    traj, info = analysis.hil_trajectory(record, 100, 1e-3)
    assert info == {"rows": 120, "skipped_periods": 0, "covered_s": pytest.approx(0.1), "complete": True}
    np.testing.assert_array_equal(traj["q"], record["q"][:100])
    np.testing.assert_allclose(traj["t"], np.arange(100) * 1e-3)


def test_realtime_record_with_skipped_periods_is_interpolated_onto_the_grid() -> None:
    t = np.delete(np.arange(100) * 1e-3, [10, 11, 50])  # three overrun periods: no row
    traj, info = analysis.hil_trajectory(_record(t), 100, 1e-3)
    assert info["skipped_periods"] == 3 and info["complete"]
    # q is linear in t, so the interpolation is exact.
    np.testing.assert_allclose(traj["q"], np.outer(np.arange(100) * 1e-3, np.arange(1, 7)), atol=1e-12)


def test_a_run_cut_short_is_held_at_its_last_row_and_marked_incomplete() -> None:
    traj, info = analysis.hil_trajectory(_record(np.arange(40) * 1e-3), 100, 1e-3)
    assert not info["complete"] and info["rows"] == 40
    np.testing.assert_array_equal(traj["q"][40:], np.repeat(traj["q"][39:40], 60, axis=0))


def test_timing_figures_in_microseconds_from_the_runtime_stats() -> None:
    stats = {
        "rate_hz": 998.7,
        "cycles": 5000.0,
        "overruns": 2.0,
        "skipped_periods": 3.0,
        "period_median_s": 1e-3,
        "period_p99_s": 1.2e-3,
        "period_max_s": 4e-3,
        "compute_median_s": 4e-5,
        "compute_p99_s": 9e-5,
        "compute_max_s": float("nan"),
        "fallbacks": 7.0,
        "bus_dropped": 0.0,
        "telemetry_dropped": 1.0,
    }
    figures = analysis.timing_figures(stats, _record(np.arange(10) * 1e-3), 1e-3)
    assert figures["period_us"] == {"median": 1000.0, "p99": 1200.0, "max": 4000.0}
    assert figures["compute_us"] == {"median": 40.0, "p99": 90.0, "max": None}  # NaN: not reported
    assert figures["exchange_us"]["median"] == 500.0
    assert (figures["rate_hz"], figures["cycles"], figures["overruns"], figures["skipped_periods"]) == (
        998.7,
        5000,
        2,
        3,
    )
    assert figures["bus"] == {"dropped": 0} and figures["telemetry_dropped"] == 1


def test_compare_scores_both_runs_and_normalizes_between_them() -> None:
    from models.conditions import load_conditions
    from models.robots import load_robot

    robot = load_robot("ur5_paper")
    condition = next(c for c in load_conditions(None, robot=robot) if c.name == "C1")
    t = np.arange(3000) * 1e-3
    q_ref = np.tile(np.array(condition.amplitude_rad) * 0.1, (t.size, 1))
    sim = {"t": t, "q": q_ref - 0.001, "q_ref": q_ref, "qd": np.zeros_like(q_ref), "within_limits": np.asarray(True)}
    hil = {**sim, "q": q_ref - 0.002, "fallback": np.zeros(t.size)}
    result = analysis.compare(robot, condition, hil, sim, None)
    assert result["relative"]["rmse"] == pytest.approx(1.0)  # twice the error
    assert result["composite"]["hil"] > result["composite"]["sim"]
    assert result["within_limits"] == {"hil": True, "sim": True}
    assert result["trajectory_rms_diff_deg"] == pytest.approx(np.degrees(0.001))
    faulted = analysis.compare(robot, condition, hil, sim, "velocity_limit: ...")
    assert faulted["within_limits"]["hil"] is False


def test_stale_private_directories_of_dead_demos_are_removed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("tempfile.gettempdir", lambda: str(tmp_path))
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True
    ).stdout.strip()
    stale, live, foreign = tmp_path / f"{WORK_PREFIX}old", tmp_path / f"{WORK_PREFIX}live", tmp_path / f"{WORK_PREFIX}x"
    for directory, owner in ((stale, dead), (live, str(os.getpid()))):
        (directory / "bus").mkdir(parents=True)
        (directory / OWNER_FILE).write_text(owner)
    foreign.mkdir()  # no owner file: not the demo's, left alone
    assert remove_stale_work_dirs() == [stale]
    assert not stale.exists() and live.exists() and foreign.exists()


def test_gui_mirror_sets_the_joints_from_the_telemetry_sample() -> None:
    pybullet = pytest.importorskip("pybullet")
    from models.demo.view import ArmMirror

    class Sample:
        values = True

        def __getitem__(self, name: str) -> np.ndarray:
            return np.array([0.1, -0.2, 0.3, -0.4, 0.5, -0.6])

    class Watch:
        sample = Sample()

    mirror = ArmMirror("ur5_paper", connection=pybullet.DIRECT)
    try:
        mirror.show(Watch())
        positions = [pybullet.getJointState(mirror._body, j, physicsClientId=mirror._client)[0] for j in mirror._joints]
        np.testing.assert_allclose(positions, Sample()["q"])
    finally:
        mirror.close()


def test_gui_without_a_display_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    from models.demo.view import NoDisplayError, check_display

    monkeypatch.delenv("DISPLAY", raising=False)
    with pytest.raises(NoDisplayError, match="--gui: no display") as caught:
        check_display()
    assert caught.value.exit_code == 2 and "\n" not in str(caught.value)
