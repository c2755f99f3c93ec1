"""The automatic gain design (gain set 'designed'): gains for any arm from its URDF, each linear law
checked by the delay margin, a design that cannot pass refused with the reason."""

from __future__ import annotations

import numpy as np
import pytest

import models.feedback.design as design
from models.delay_margin import delay_margin
from models.feedback import make_law
from models.robots import load_robot

UR5_PAPER = load_robot("ur5_paper")


def test_envelope_finds_the_folded_elbow_and_the_stretched_shoulder() -> None:
    env = design.envelope(UR5_PAPER)
    assert np.all(env.m_min > 0) and np.all(env.m_min <= env.m_max)
    assert env.m_min[2] == pytest.approx(2.8e-3, rel=0.1)  # the elbow when the arm folds
    assert env.m_max[1] == pytest.approx(0.387, rel=0.05)


def test_pd_gains_follow_the_budget_equations() -> None:
    env = design.envelope(UR5_PAPER)
    gains, bandwidth = design.law_gains("pd", env)
    budget = design.C_V * env.m_min / env.period_s
    assert np.all(gains["kd"] <= budget + 1e-12)
    assert np.all(gains["kp"] <= gains["kd"] ** 2 / (4 * design.ZETA**2 * env.m_max) + 1e-9)
    assert np.all(gains["kp"] <= env.torque_limit_nm / design.E_SAT_RAD + 1e-9)
    np.testing.assert_allclose(bandwidth, np.sqrt(gains["kp"] / env.m_max))


@pytest.mark.parametrize("robot_name", ["ur5_paper", "panda"])
def test_designed_pd_and_adrc_exist_for_any_arm_and_hold_the_delay(robot_name: str) -> None:
    robot = load_robot(robot_name)
    for name in ("pd", "adrc"):
        law = make_law(name, robot, 1e-3, gain_set="designed")
        assert law.n_joints == robot.n_joints
        report = delay_margin(law, robot, 1)
        assert report.holds and report.unstable_poses == 0, (name, report.as_dict())


def test_a_design_that_cannot_pass_is_refused_with_the_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    design._design_by_key.cache_clear()
    monkeypatch.setattr(design, "C_V", 4.0)  # a damping budget beyond the delayed loop's limit of 1
    monkeypatch.setattr(design, "RETRIES", 0)
    try:
        with pytest.raises(design.DesignError, match=r"'ur5_paper', law 'pd': the delayed loop .* unstable at \d+"):
            make_law("pd", UR5_PAPER, 1e-3, gain_set="designed")
    finally:
        design._design_by_key.cache_clear()
