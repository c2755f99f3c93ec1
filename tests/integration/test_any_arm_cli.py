"""``--robot URDF`` through the chain (docs/any_arm.md): a robot given as a URDF file, not a built-in
name, runs ``hil experiment --plant hil``: the target loads the file and drives the model's joints,
the simulation twin (another process) loads the same file. The arm is a copy of ur5_paper's URDF, so
the shipped bundles (models/bundles/<robot name>/) and gain sets apply; a short condition, one law.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from models.robots import urdf_path

SHORT = """\
defaults: {duration_s: 0.3, phase_s: 2.5, initial_state: reference, disturbance: null}
conditions:
  - name: C1short
    amplitude_rad: [-pi/4, pi/6, -pi/6, -pi/4, pi/2, pi/2]
"""


def test_hil_experiment_on_a_urdf_robot(tmp_path: Path) -> None:
    arm = tmp_path / "my_arm.urdf"
    arm.write_text(urdf_path("ur5_paper").read_text())
    (tmp_path / "short.yaml").write_text(SHORT)
    out = tmp_path / "out"
    args = ["experiment", "--plant", "hil", "--laws", "pd", "--modes", "fb"]
    args += ["--robot", str(arm), "--conditions", "short.yaml", "--out", str(out), "--no-plots"]
    result = subprocess.run(
        [sys.executable, "-m", "hil_runtime.cli", *args], capture_output=True, text=True, cwd=tmp_path, timeout=600
    )
    assert result.returncode == 0, result.stderr[-2000:]
    results = json.loads((out / "results.json").read_text())
    assert results["all_runs_finite_and_within_limits"]
    (run,) = results["runs"]
    assert run["hil"]["fault"] is None and run["hil"]["rows"] == 300
    assert (out / "sim" / "results.json").is_file()  # the twin loaded the same file in its process
