"""The main job's LMPC path on every shipped bundle, and the tolerance of the law-parameter check.

A bundle stores the law parameters it was exported with; the experiment rebuilds the law from the
gain set and compares. A synthesized law (H-infinity's gamma) differs at ~1e-8 between numerical
stacks, so an exact comparison broke `hil experiment` on a fresh install (issue 9).
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

pytest.importorskip("torch")

from hil_runtime.bundle import BundleError
from models.feedback import LAW_NAMES, make_law
from models.lmpc.controller import (
    SHIPPED_BUNDLES,
    make_lmpc_controller,
    params_difference,
)
from models.robots import load_robot

ROBOT = load_robot("ur5_paper")


def test_params_difference_tolerates_solver_noise_and_catches_real_changes() -> None:
    law = {"gamma": [0.7341824213225467, 1.2], "discretization": "tustin", "gravity_compensation": True}
    noisy = {"gamma": [0.7341824128066271, 1.2], "discretization": "tustin", "gravity_compensation": True}
    assert params_difference(noisy, law) is None
    assert "params.gamma[1]" in params_difference({**noisy, "gamma": [0.7341824128, 1.21]}, law)
    assert "discretization" in params_difference({**noisy, "discretization": "zoh"}, law)
    assert "gravity_compensation" in params_difference({**noisy, "gravity_compensation": False}, law)
    assert "fields" in params_difference({**noisy, "extra": 1}, law)
    assert params_difference({"k": 1}, {"k": 1.0}) is None
    assert params_difference({"k": True}, {"k": 1}) is not None


@pytest.mark.parametrize("law_name", LAW_NAMES)
def test_every_shipped_bundle_matches_the_law_of_its_gain_set(law_name: str) -> None:
    manifest = json.loads((SHIPPED_BUNDLES / ROBOT.name / law_name / "manifest.json").read_text())
    law = make_law(law_name, ROBOT, manifest["period_s"], manifest["law"]["gain_set"])
    assert params_difference(manifest["law"]["params"], law.params) is None
    make_lmpc_controller(law, ROBOT)  # loads and checks exactly as the experiment does


def test_a_bundle_for_other_gains_is_still_refused() -> None:
    with pytest.raises(BundleError, match=r"parameters differ .*bundle vs law params\."):
        make_lmpc_controller(make_law("adrc", ROBOT, 1e-3, "paper"), ROBOT)


def test_the_main_job_lmpc_path_runs_every_shipped_bundle(tmp_path: Path, hil_command: list[str]) -> None:
    conditions = tmp_path / "short.yaml"
    conditions.write_text(
        "conditions:\n  - name: S1\n    amplitude_rad: [-pi/4, pi/6, -pi/6, -pi/4, pi/2, pi/2]\n"
        "    duration_s: 0.2\n    phase_s: 2.5\n    frequency_hz: 0.1\n    initial_state: reference\n"
        "    disturbance: {time_s: 0.1, torque_nm: [1, 1, 5, 5, 10, 10], duration_s: 2.0e-5}\n"
    )
    out = tmp_path / "out"
    done = subprocess.run(
        [
            *hil_command,
            "experiment",
            "--modes",
            "lmpc",
            "--conditions",
            str(conditions),
            "--timing-cycles",
            "20",
            "--no-plots",
            "--no-trajectories",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        check=False,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"wrote {out}/results.json, table.md" in done.stderr and "plots/" not in done.stderr  # only what it wrote
    assert sorted(p.name for p in out.iterdir()) == ["results.json", "table.md"]
    results = json.loads((out / "results.json").read_text())
    runs = {(r["law"], r["mode"]) for r in results["runs"]}
    assert runs == {(law, "lmpc") for law in LAW_NAMES}
    assert all(r["finite"] and r["within_limits"] for r in results["runs"])


def test_a_bundle_for_another_urdf_is_refused(tmp_path: Path) -> None:

    shutil.copytree(SHIPPED_BUNDLES / ROBOT.name / "pd", tmp_path / "pd")
    manifest = json.loads((tmp_path / "pd" / "manifest.json").read_text())
    manifest["robot"]["urdf_sha256"] = "0" * 64
    (tmp_path / "pd" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match="urdf_sha256"):
        make_lmpc_controller(make_law("pd", ROBOT, 1e-3), ROBOT, bundle_dir=tmp_path)


def test_a_bundle_directory_without_the_law_names_the_typed_path(tmp_path: Path) -> None:
    with pytest.raises(BundleError, match=rf"^bundle directory {tmp_path}: no bundle for law 'pd'"):
        make_lmpc_controller(make_law("pd", ROBOT, 1e-3), ROBOT, bundle_dir=tmp_path)
