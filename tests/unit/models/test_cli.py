"""The hil CLI: bad input gives one line and exit code 2; the experiment writes its outputs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest


def hil(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "hil_runtime.cli", *args], capture_output=True, text=True, cwd=cwd, timeout=600
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["experiment", "--laws", "pd,foo"], "--laws: unknown 'foo'"),
        (["experiment", "--robot", "ur6"], "robot: unknown name 'ur6'"),
        (
            ["experiment", "--robot", "ur5", "--gains", "stabilized"],
            "gain set 'stabilized' holds the gains of 'ur5_paper', not of robot 'ur5'",
        ),
        (
            ["stability", "pd", "--robot", "ur5", "--gains", "stabilized"],
            "not of robot 'ur5' (6 joints); pass kp, kd for it, or use gain set 'designed'",
        ),
        (["experiment", "--conditions", "missing.yaml"], "missing.yaml: file not found"),
        (["experiment", "--modes", "xyz"], "--modes: unknown 'xyz'"),
    ],
)
def test_bad_input_is_one_line_exit_2(args: list[str], message: str, tmp_path: Path) -> None:
    result = hil(*args, cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr
    assert "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_malformed_urdf_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "arm.urdf"
    bad.write_text("<robot name='x'><link name='a'/><joint name='j' type='revolute'><parent link='a'/>")
    result = hil("experiment", "--robot", str(bad), cwd=tmp_path)
    assert result.returncode == 2 and "arm.urdf: not valid XML" in result.stderr
    assert "Traceback" not in result.stderr


def test_experiment_writes_table_results_trajectories_and_plots(tmp_path: Path) -> None:
    conditions = tmp_path / "short.yaml"
    conditions.write_text(
        "defaults: {duration_s: 0.6, disturbance: {time_s: 0.3, torque_nm: [1, 1, 5, 5, 10, 10], duration_s: 2.0e-5}}\n"
        "conditions:\n  - {name: S1, amplitude_rad: [-pi/4, pi/6, -pi/6, -pi/4, pi/2, pi/2], frequency_hz: 0.5}\n"
    )
    out = tmp_path / "out"
    result = hil(
        "experiment",
        "--laws",
        "pd,pid",
        "--conditions",
        str(conditions),
        "--out",
        str(out),
        "--timing-cycles",
        "50",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    results = json.loads((out / "results.json").read_text())
    assert set(results["table"]) == {"pd", "pid"}
    assert len(results["runs"]) == 6 and all(r["finite"] for r in results["runs"])  # fb, hmpc, lmpc by default
    table = (out / "table.md").read_text()
    assert "| PD |" in table and "η_H (%)" in table and "η_L (%)" in table
    run = dict(__import__("numpy").load(out / "trajectories" / "pd_fb_S1.npz"))
    assert run["q"].shape == (600, 6) and set(run) >= {"t", "q", "qd", "q_ref", "tau"}
    assert (out / "plots" / "pd_S1.png").stat().st_size > 1000
