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


def test_the_pandas_rate_aware_lmpc_starts_from_the_torque_holding_the_arm() -> None:
    """The Panda's bundles read tau_prev (docs/lmpc.md §11): a simulated run starts from the torque holding
    the arm at rest (the nominal gravity at q0), as the runtime starts from the drives' held set-point; from
    zero the arm would fall while the torque climbs at 1 N·m per cycle."""
    import numpy as np

    from hil_runtime.rate_limit import max_torque_step_nm
    from models.default_conditions import default_conditions
    from models.dynamics import make_dynamics

    robot = load_robot("panda")
    law = make_law("pd", robot, 1e-3, "designed")
    controller = make_lmpc_controller(law, robot)
    assert controller.bundle.takes_previous_torque
    condition = default_conditions(robot)[0]
    q0, qd0, qdd0 = (np.atleast_2d(v) for v in condition.reference(0.0))
    controller.reset(q0)
    held = make_dynamics(robot).gravity(q0[0])
    assert np.abs(held).max() > 5.0  # a start from zero would be refused below
    tau = controller(0.0, q0, np.zeros_like(q0), q0, qd0, qdd0)[0]
    assert (np.abs(tau - held) <= max_torque_step_nm(robot.torque_rate_nm_s, 1e-3) * (1 + 1e-9)).all()
