"""``hil demo --robot ur5|panda`` out of the box (issue 25, docs/any_arm.md): the shipped bundles of
the real arms run as the default demo does, lock-step, two processes over the ipc bus, for a short
part of the robot's default condition C1: every joint of the arm in the records (seven for the
Panda, its fingers locked by the target), no fault, inside the limits, the drives quick-stopped."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from models.robots import load_robot

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the ipc bus is Linux only")

DURATION_S = 0.3


@pytest.fixture
def private_tmp() -> Iterator[Path]:
    """A short TMPDIR for the demo alone (its bus sockets live there: Unix paths are short)."""
    path = Path(tempfile.mkdtemp(prefix="hda-", dir="/tmp"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.mark.parametrize("robot_name", ["ur5", "panda"])
def test_hil_demo_runs_the_shipped_bundles_of_a_real_arm(
    robot_name: str, tmp_path: Path, private_tmp: Path, hil_command: list[str]
) -> None:
    out = tmp_path / "demo"
    run = subprocess.run(
        [*hil_command, "demo", "--robot", robot_name, "--headless", "--duration", str(DURATION_S), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
        env={**os.environ, "TMPDIR": str(private_tmp)},
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert "Traceback" not in run.stderr
    results = json.loads((out / "results.json").read_text())
    robot = load_robot(robot_name)
    assert results["fault"] is None and results["coverage"]["complete"]
    assert results["scores"]["within_limits"] == {"hil": True, "sim": True}
    stop = results["shutdown"]
    assert stop["runtime_exit_code"] == 0 and stop["target_exit_code"] == 0
    assert stop["drives_operation_enabled_after_stop"] == [False] * robot.n_joints
    with np.load(out / "run.npz") as data:
        schema = json.loads(str(data["schema"]))
        joints = list(data["joints"])
    assert schema["robot"] == robot_name and joints == list(robot.joint_names)
    with np.load(out / "runtime_record.npz") as data:
        assert data["q"].shape[1] == robot.n_joints
        assert data["q"].shape[0] >= round(DURATION_S / 1e-3)
