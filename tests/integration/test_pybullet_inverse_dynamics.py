"""One URDF, three consumers: the project's dynamics (own RNE and pinocchio backends) agree with
pybullet's inverse dynamics on the arm as the sim target loads it (sim_target.plant.load_arm)."""

from __future__ import annotations

import numpy as np
import pybullet
import pytest

from models.dynamics import make_dynamics
from models.robots import load_robot, urdf_path
from sim_target.plant import load_arm


def _pybullet_arm(name: str):
    client = pybullet.connect(pybullet.DIRECT)
    body = load_arm(client, urdf_path(name))
    pybullet.setGravity(0.0, 0.0, -9.81, physicsClientId=client)
    movable = [
        (pybullet.getJointInfo(body, j, physicsClientId=client)[1].decode(), j)
        for j in range(pybullet.getNumJoints(body, physicsClientId=client))
        if pybullet.getJointInfo(body, j, physicsClientId=client)[2] != pybullet.JOINT_FIXED
    ]
    return client, body, [name for name, _ in movable]


@pytest.mark.parametrize("robot_name", ["ur5_paper", "ur5", "panda"])
@pytest.mark.parametrize("backend", ["rne", "pinocchio"])
def test_inverse_dynamics_matches_pybullet(robot_name: str, backend: str) -> None:
    robot = load_robot(robot_name)
    dyn = make_dynamics(robot, backend=backend)
    client, body, pb_joints = _pybullet_arm(robot_name)
    try:
        # pybullet's vectors cover every movable joint in URDF order; the Panda's fingers are
        # extra (prismatic, held at 0 as models locks them). Map the chain's joints into them.
        columns = [pb_joints.index(name) for name in robot.joint_names]
        assert len(pb_joints) - len(columns) == (2 if robot_name == "panda" else 0)
        rng = np.random.default_rng(11)
        for _ in range(20):
            q, qd, qdd = (rng.uniform(-1.5, 1.5, robot.n_joints) for _ in range(3))
            full = [np.zeros(len(pb_joints)) for _ in range(3)]
            for vector, value in zip(full, (q, qd, qdd), strict=True):
                vector[columns] = value
            tau_pb = np.array(
                pybullet.calculateInverseDynamics(body, *(v.tolist() for v in full), physicsClientId=client)
            )[columns]
            tau = dyn.inverse_dynamics(q, qd, qdd)
            scale = max(1.0, float(np.abs(tau_pb).max()))
            np.testing.assert_allclose(tau, tau_pb, rtol=0, atol=1e-9 * scale)
    finally:
        pybullet.disconnect(client)


def test_the_check_would_catch_pybullets_phantom_flange_mass() -> None:
    # Without load_arm's fix the flange (no <inertial>) weighs 1 kg in pybullet: 0.5 N·m or more.
    client = pybullet.connect(pybullet.DIRECT)
    try:
        body = pybullet.loadURDF(
            str(urdf_path("ur5_paper")),
            useFixedBase=True,
            flags=pybullet.URDF_USE_INERTIA_FROM_FILE,
            physicsClientId=client,
        )
        pybullet.setGravity(0.0, 0.0, -9.81, physicsClientId=client)
        q = [0.0, 1.0, 0.5, 0.0, 0.0, 0.0]
        tau_pb = np.array(pybullet.calculateInverseDynamics(body, q, [0.0] * 6, [0.0] * 6, physicsClientId=client))
        tau = make_dynamics(load_robot("ur5_paper")).gravity(np.array(q))
        assert np.abs(tau - tau_pb).max() > 0.5
    finally:
        pybullet.disconnect(client)
