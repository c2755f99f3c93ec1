"""The project's RNEIDA/RNEFDA against pinocchio's rnea/crba/aba (built independently from the URDF)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from models.dynamics import make_dynamics
from models.robots import load_robot
from models.robots.description import RobotModel

RTOL = 1e-9


def _fmt(values: np.ndarray) -> str:
    return " ".join(repr(float(v)) for v in values)


def random_chain_urdf(n_joints: int, seed: int, path: Path) -> Path:
    """A random serial chain: random joint placements (rpy and xyz), axes, masses, COMs and full inertia
    tensors, with a fixed tool link at the end so fixed-body merging is exercised too."""
    rng = np.random.default_rng(seed)
    lines = ['<?xml version="1.0"?>', f'<robot name="random{n_joints}_{seed}">', '<link name="l0"/>']
    for i in range(1, n_joints + 1):
        xyz, rpy, axis = rng.uniform(-0.3, 0.3, 3), rng.uniform(-np.pi, np.pi, 3), rng.normal(size=3)
        a = rng.normal(size=(3, 3))
        inertia = a @ a.T * 0.01 + np.eye(3) * 1e-3
        com = rng.uniform(-0.1, 0.1, 3)
        lines += [
            f'<joint name="j{i}" type="revolute"><parent link="l{i - 1}"/><child link="l{i}"/>',
            f'<origin xyz="{_fmt(xyz)}" rpy="{_fmt(rpy)}"/>',
            f'<axis xyz="{_fmt(axis / np.linalg.norm(axis))}"/>',
            '<limit lower="-3" upper="3" effort="100" velocity="3"/></joint>',
            f'<link name="l{i}"><inertial><origin xyz="{_fmt(com)}" rpy="0.1 0.2 0.3"/>',
            f'<mass value="{float(rng.uniform(0.2, 3.0))!r}"/>',
            f'<inertia ixx="{float(inertia[0, 0])!r}" ixy="{float(inertia[0, 1])!r}" ixz="{float(inertia[0, 2])!r}" '
            f'iyy="{float(inertia[1, 1])!r}" iyz="{float(inertia[1, 2])!r}" izz="{float(inertia[2, 2])!r}"/>'
            "</inertial></link>",
        ]
    lines += [
        f'<joint name="tool_joint" type="fixed"><parent link="l{n_joints}"/><child link="tool"/>',
        '<origin xyz="0.05 0.02 0.1" rpy="0.3 0 0.2"/></joint>',
        '<link name="tool"><inertial><origin xyz="0 0 0.02"/><mass value="0.3"/>',
        '<inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.002"/></inertial></link>',
        "</robot>",
    ]
    path.write_text("\n".join(lines))
    return path


def pinocchio_from_urdf(robot: RobotModel):
    model = pin.buildModelFromUrdf(str(robot.urdf_path))
    extra = [model.getJointId(name) for name in list(model.names)[1:] if name not in robot.joint_names]
    if extra:  # e.g. the Panda's fingers, locked at zero as in our description
        model = pin.buildReducedModel(model, extra, pin.neutral(model))
    model.gravity = pin.Motion(robot.gravity_m_s2, np.zeros(3))
    return model


def robots(tmp_path_factory: pytest.TempPathFactory) -> list[RobotModel]:
    out = [load_robot(name) for name in ("ur5_paper", "ur5", "panda")]
    folder = tmp_path_factory.mktemp("chains")
    out += [load_robot(random_chain_urdf(n, seed=n, path=folder / f"chain{n}.urdf")) for n in range(1, 13)]
    return out


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-12))


@pytest.fixture(scope="module")
def all_robots(tmp_path_factory: pytest.TempPathFactory) -> list[RobotModel]:
    return robots(tmp_path_factory)


def test_chain_sizes(all_robots: list[RobotModel]) -> None:
    assert [r.n_joints for r in all_robots] == [6, 6, 7, *range(1, 13)]


def test_own_rne_matches_pinocchio_rnea_crba_aba(all_robots: list[RobotModel]) -> None:
    rng = np.random.default_rng(7)
    for robot in all_robots:
        own = make_dynamics(robot, "rne")
        model = pinocchio_from_urdf(robot)
        data = model.createData()
        batch = 8
        q, qd, qdd, tau = (rng.uniform(-2, 2, (batch, robot.n_joints)) for _ in range(4))
        ref_tau = np.array([pin.rnea(model, data, q[b], qd[b], qdd[b]) for b in range(batch)])
        ref_m = np.array([pin.crba(model, data, q[b]) for b in range(batch)])
        ref_m = np.triu(ref_m) + np.transpose(np.triu(ref_m, 1), (0, 2, 1))
        ref_qdd = np.array([pin.aba(model, data, q[b], qd[b], tau[b]) for b in range(batch)])
        ref_g = np.array([pin.computeGeneralizedGravity(model, data, q[b]) for b in range(batch)])
        assert _rel(own.inverse_dynamics(q, qd, qdd), ref_tau) < RTOL, robot.name
        assert _rel(own.mass_matrix(q), ref_m) < RTOL, robot.name
        assert _rel(own.forward_dynamics(q, qd, tau), ref_qdd) < RTOL, robot.name
        assert _rel(own.gravity(q), ref_g) < RTOL, robot.name
        # single state in, single state out
        assert own.inverse_dynamics(q[0], qd[0], qdd[0]).shape == (robot.n_joints,)
        assert _rel(own.inverse_dynamics(q[0], qd[0], qdd[0]), ref_tau[0]) < RTOL


def test_end_effector_wrench_matches_pinocchio_jacobian_transpose() -> None:
    """tau = ID - J^T w, with w the wrench the environment applies at the end effector (its frame)."""
    robot = load_robot("ur5_paper")
    own = make_dynamics(robot, "rne")
    model = pinocchio_from_urdf(robot)
    data = model.createData()
    ee = model.getFrameId("flange")
    rng = np.random.default_rng(3)
    for _ in range(5):
        q, qd, qdd = (rng.uniform(-2, 2, 6) for _ in range(3))
        wrench = rng.normal(size=6) * 10
        jac = pin.computeFrameJacobian(model, data, q, ee, pin.LOCAL)
        expected = pin.rnea(model, data, q, qd, qdd) - jac.T @ wrench
        assert _rel(own.inverse_dynamics(q, qd, qdd, wrench), expected) < RTOL
        assert _rel(make_dynamics(robot, "pinocchio").inverse_dynamics(q, qd, qdd, wrench), expected) < RTOL


def test_pinocchio_backend_matches_own(all_robots: list[RobotModel]) -> None:
    rng = np.random.default_rng(11)
    for robot in all_robots[:3]:
        own, pin_dyn = make_dynamics(robot, "rne"), make_dynamics(robot, "pinocchio")
        q, qd, tau = (rng.uniform(-2, 2, (4, robot.n_joints)) for _ in range(3))
        assert _rel(own.forward_dynamics(q, qd, tau), pin_dyn.forward_dynamics(q, qd, tau)) < RTOL
        assert _rel(own.nonlinear_effects(q, qd), pin_dyn.nonlinear_effects(q, qd)) < RTOL


def test_payload_and_scaling_change_the_dynamics_as_physics_says() -> None:
    robot = load_robot("ur5_paper")
    heavy = robot.with_payload(0.5)
    q = np.array([0.0, np.pi / 2, 0.0, 0.0, 0.0, 0.0])  # upper arm horizontal: gravity torque is plain lever arm
    extra = make_dynamics(heavy).gravity(q) - make_dynamics(robot).gravity(q)
    lever = 0.2 + 0.2 + 0.17  # shoulder to flange along the now-horizontal arm (wrist 1 and 3 are sideways)
    assert extra[1] == pytest.approx(-0.5 * 9.81 * lever, rel=1e-9)
    scaled = robot.scaled(mass_scale=2.0)
    assert make_dynamics(scaled).gravity(q) == pytest.approx(2 * make_dynamics(robot).gravity(q), rel=1e-12)


def test_asymmetric_joint_ranges_are_kept() -> None:
    panda = load_robot("panda")
    assert panda.position_lower_rad[3] == pytest.approx(-3.0718)
    assert panda.position_upper_rad[3] == pytest.approx(-0.0698)
    assert panda.position_limit_ratio(np.zeros(7))[3] > 1.0  # q4 = 0 is outside the Panda's range
    paper = load_robot("ur5_paper")
    assert paper.position_range_rad is None
    assert paper.position_limit_ratio(paper.position_limit_rad) == pytest.approx(np.ones(6))
