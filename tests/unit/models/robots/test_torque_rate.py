"""The per-robot torque-rate bound (hil_runtime/rate_limit.py, models/robots/data/robots.yaml,
docs/any_arm.md "Torque-rate bound"): each robot's rule, and the deployable verdict, the HMPC's rate
box and a bundle's limiter reading the same value."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil_runtime.bundle import PolicyBundle
from hil_runtime.bundle_security import seal_manifest
from hil_runtime.rate_limit import TorqueRateLimiter, max_torque_step_nm
from models.experiment import verdicts
from models.feedback import make_law
from models.hmpc.config import FORMULATIONS, HMPCConfig
from models.hmpc.solver import HMPCSolver
from models.robots import load_robot, urdf_path

SHIPPED_PD = Path(__file__).resolve().parents[4] / "models" / "bundles" / "ur5_paper" / "pd"


def test_each_robot_s_bound() -> None:
    # the Panda: libfranka's kMaxTorqueRate, 1000 N·m/s on all seven joints (its 12 N·m wrists too)
    np.testing.assert_allclose(load_robot("panda").torque_rate_nm_s, [1000.0] * 7)
    # the real UR5: no published figure, libfranka's unscaled (docs/any_arm.md)
    np.testing.assert_allclose(load_robot("ur5").torque_rate_nm_s, [1000.0] * 6)
    # ur5_paper keeps the rule its bundles and tables were measured with: 1000 N·m/s per 87 N·m of limit
    paper = load_robot("ur5_paper")
    np.testing.assert_allclose(paper.torque_rate_nm_s, 1000.0 * paper.torque_limit_nm / 87.0)
    # any other URDF (here ur5_paper's own file by path): the documented default, 1000 N·m/s
    np.testing.assert_allclose(load_robot(str(urdf_path("ur5_paper"))).torque_rate_nm_s, [1000.0] * 6)
    # a payload or a mismatched model of the arm keeps its bound
    np.testing.assert_allclose(load_robot("panda").with_payload(1.0).scaled(1.2).torque_rate_nm_s, [1000.0] * 7)


def test_the_verdict_and_the_hmpc_read_the_robot_s_bound() -> None:
    panda = load_robot("panda")
    law = make_law("pd", panda, 1e-3, "designed")
    solver = HMPCSolver(law, panda, HMPCConfig(**FORMULATIONS["deployable"]))
    assert solver.rate_step_nm is not None
    step = max_torque_step_nm(panda.torque_rate_nm_s, 1e-3)
    np.testing.assert_allclose(solver.rate_step_nm, step, rtol=1e-5)
    np.testing.assert_allclose(step, [1.0] * 7)  # 1 N·m per 1 ms cycle on every joint
    # the verdict: a 0.9 N·m step on the 12 N·m wrist is inside the Panda's bound (the old scaled rule
    # allowed 0.14 N·m there), a 1.1 N·m step is not
    n = panda.n_joints

    def run(wrist_step_nm: float) -> dict[str, Any]:
        steps = [0.1] * n
        steps[-1] = wrist_step_nm
        effort = {"chatter_nm": [0.01] * n, "max_torque_step_nm": steps, "peak_torque_ratio": [0.5] * n}
        return {"law": "pd", "condition": "C", "mode": "hmpc", "finite": True, "within_limits": True, "effort": effort}

    runs = [run(0.9), run(1.1)]
    verdicts(runs, panda, 1e-3)
    assert runs[0]["verdict"]["deployable"], runs[0]["verdict"]
    assert not runs[1]["verdict"]["deployable"] and "torque rate" in runs[1]["verdict"]["reasons"][0]


def test_a_bundle_carries_the_bound_and_an_older_one_keeps_the_scaled_rule(tmp_path: Path) -> None:
    older = PolicyBundle.load(SHIPPED_PD)  # written before limits.torque_rate_nm_s existed
    np.testing.assert_allclose(older.torque_rate_nm_s, 1000.0 * older.torque_limit_nm / 87.0)
    path = tmp_path / "pd"
    shutil.copytree(SHIPPED_PD, path)
    raw = json.loads((path / "manifest.json").read_text())
    raw["limits"]["torque_rate_nm_s"] = [1000.0, 1000.0, 900.0, 800.0, 700.0, 600.0]
    (path / "manifest.json").write_text(json.dumps(seal_manifest(raw)))
    bundle = PolicyBundle.load(path)
    np.testing.assert_allclose(bundle.torque_rate_nm_s, [1000.0, 1000.0, 900.0, 800.0, 700.0, 600.0])
    np.testing.assert_allclose(TorqueRateLimiter(bundle.torque_rate_nm_s, 1e-3).step_nm, [1, 1, 0.9, 0.8, 0.7, 0.6])


@pytest.mark.parametrize("rates", [[1000.0] * 5, [1000.0] * 5 + [0.0]])
def test_a_bad_bound_in_a_manifest_is_refused(tmp_path: Path, rates: list[float]) -> None:
    from hil_runtime.bundle import BundleError

    path = tmp_path / "pd"
    shutil.copytree(SHIPPED_PD, path)
    raw = json.loads((path / "manifest.json").read_text())
    raw["limits"]["torque_rate_nm_s"] = rates
    (path / "manifest.json").write_text(json.dumps(seal_manifest(raw)))
    with pytest.raises(BundleError, match="torque_rate_nm_s") as info:
        PolicyBundle.load(path)
    assert "\n" not in str(info.value)


def test_the_deployable_formulation_per_robot() -> None:
    from models.hmpc.config import DEPLOYABLE_PREDICTION_STEP_S, formulation_options

    # ur5_paper: the control period, as its bundles and tables were measured; any other arm: 10 ms steps
    assert "prediction_step_s" not in formulation_options("deployable", "ur5_paper")
    for name in ("ur5", "panda", "my_arm"):
        assert formulation_options("deployable", name)["prediction_step_s"] == DEPLOYABLE_PREDICTION_STEP_S
        assert formulation_options("deployable", name)["torque_rate_limit"] == "franka"
    assert formulation_options("absolute", "panda") == {}


@pytest.mark.heavy
@pytest.mark.parametrize("robot_name", ["ur5", "panda"])
def test_the_deployable_hmpc_stays_inside_the_limits_under_the_real_bound(robot_name: str) -> None:
    """The pipeline's first training condition through the disturbance (benchmarks/hmpc_rate_bound_limits.py
    for every law): PD's deployable HMPC under the robot's rate bound stays inside its velocity limits with
    the formulation's 10 ms prediction step, and limit-cycles out of them with 1 ms steps."""
    from dataclasses import replace

    from models.hmpc import make_hmpc_controller
    from models.hmpc.config import formulation_options
    from models.lmpc.paper_range import paper_range_conditions
    from models.lmpc.structured import StructuredConfig
    from models.sim import SimConfig, simulate

    robot = load_robot(robot_name)
    conditions = [replace(c, duration_s=2.4) for c in paper_range_conditions(robot, 1, StructuredConfig().train_seed)]
    law = make_law("pd", robot, 1e-3, "designed")
    options = formulation_options("deployable", robot.name)
    ratio = {}
    for step_s in (options["prediction_step_s"], 1e-3):
        controller = make_hmpc_controller(law, robot, **{**options, "prediction_step_s": step_s})
        traj = simulate(robot, controller, conditions, SimConfig(period_s=1e-3, substeps=2))
        ratio[step_s] = float(traj.velocity_ratio[0].max())
        steps = np.abs(np.diff(traj.tau[0], axis=0))
        assert (steps <= max_torque_step_nm(robot.torque_rate_nm_s, 1e-3) * (1 + 1e-9)).all()
    assert ratio[options["prediction_step_s"]] < 1.0 < ratio[1e-3], ratio


def test_a_bad_rule_in_the_registry_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    from models.errors import ModelInputError
    from models.robots import description

    where, ee, _ = description._BUILTIN["panda"]
    monkeypatch.setitem(description._BUILTIN, "panda", (where, ee, "fast"))
    with pytest.raises(ModelInputError, match=r"robots.yaml: panda: torque_rate: .*unknown rule 'fast'") as info:
        load_robot("panda")
    assert "\n" not in str(info.value)
