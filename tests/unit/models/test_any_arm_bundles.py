"""The real UR5's and the Panda's shipped bundles (issue 25, docs/any_arm.md): one per law under
models/bundles/<robot>/<law>/, each loaded and probe-checked by the runtime's loader, for the robot's
joints in order, and exported with the law its gain set `designed` makes today (a bundle of a
design that changed since is refused: the experiment and the demo would run another law)."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("onnxruntime")

from models.feedback import LAW_NAMES, make_law
from models.lmpc.controller import SHIPPED_BUNDLES, make_lmpc_controller, params_difference
from models.robots import load_robot


@pytest.mark.parametrize("robot_name", ["ur5", "panda"])
@pytest.mark.parametrize("law_name", LAW_NAMES)
def test_every_law_of_the_real_arms_ships_a_bundle_of_its_designed_law(robot_name: str, law_name: str) -> None:
    robot = load_robot(robot_name)
    manifest = json.loads((SHIPPED_BUNDLES / robot_name / law_name / "manifest.json").read_text())
    assert manifest["robot"]["name"] == robot_name
    assert manifest["robot"]["joint_names"] == list(robot.joint_names)
    assert manifest["law"]["gain_set"] == "designed"
    # the robot's torque-rate bound (hil_runtime.rate_limit), which the runtime's limiter reads from here
    assert manifest["limits"]["torque_rate_nm_s"] == robot.torque_rate_nm_s.tolist()
    law = make_law(law_name, robot, manifest["period_s"], "designed")
    assert params_difference(manifest["law"]["params"], law.params) is None
    make_lmpc_controller(law, robot)  # the runtime's loader: schema, urdf sha256, probes, saturation
