"""Theorem 1 tool: PD margins at a static pose match the closed-form values; Jacobians are right."""

from __future__ import annotations

import numpy as np
import pytest

from models.dynamics import make_dynamics
from models.errors import ModelInputError
from models.feedback import make_law
from models.robots import load_robot
from models.stability import PAPER_P, evaluate_theorem1, law_jacobians, model_terms

ROBOT = load_robot("ur5_paper")


def _gravity_jacobian(q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    dyn = make_dynamics(ROBOT, "rne")  # the project's own RNEIDA, independent of pinocchio
    cols = [(dyn.gravity(q + h * e) - dyn.gravity(q - h * e)) / (2 * h) for e in np.eye(len(q))]
    return np.stack(cols, 1)


def test_pd_margins_match_closed_form_at_a_static_pose() -> None:
    law = make_law("pd", ROBOT)
    q = np.array([0.2, 0.5, -0.4, 0.3, 0.6, 0.1])
    t = 3
    zeros = np.zeros((t, 6))
    qs = np.tile(q, (t, 1))
    beta, eps = 1e-6, 1e-3
    report = evaluate_theorem1(law, ROBOT, qs, zeros, qs, zeros, zeros, beta=beta, epsilon=eps)
    # At rest C = 0; dphi/de = Kp, dphi/de_dot = Kd.
    m_max = np.linalg.eigvalsh(make_dynamics(ROBOT).mass_matrix(q)).max()
    g_norm = np.linalg.norm(_gravity_jacobian(q), 2)
    kp, kd = np.diag(law.kp), np.diag(law.kd)
    expected = {
        "eq19": kd.diagonal().min() - beta * m_max - eps,
        "eq20": kp.diagonal().min() - g_norm - np.linalg.norm(PAPER_P, 2) / beta - eps,
        "eq21": (2 / beta) * (kd.diagonal().min() - beta * m_max) * (beta * kd.diagonal().min() - beta**2 * g_norm)
        - np.linalg.norm(beta * kp - PAPER_P, 2),
    }
    for key, value in expected.items():
        assert report.margins[key] == pytest.approx(value, rel=1e-6, abs=1e-9), key
    assert report.holds == {"eq19": True, "eq20": False, "eq21": False}


def test_coriolis_matrix_makes_mdot_minus_2c_skew_and_reproduces_the_bias() -> None:
    rng = np.random.default_rng(4)
    q, qd = rng.normal(size=(1, 6)), rng.normal(size=(1, 6))
    h = 1e-6
    mass, coriolis, _ = model_terms(ROBOT, np.concatenate([q - h * qd, q, q + h * qd]), np.tile(qd, (3, 1)))
    m_dot = (mass[2] - mass[0]) / (2 * h)
    skew = m_dot - 2 * coriolis[1]
    np.testing.assert_allclose(skew, -skew.T, atol=1e-6)
    dyn = make_dynamics(ROBOT)
    bias = dyn.nonlinear_effects(q[0], qd[0]) - dyn.gravity(q[0])
    np.testing.assert_allclose(coriolis[1] @ qd[0], bias, atol=1e-9)


def test_law_jacobians_of_pid_and_smc() -> None:
    rng = np.random.default_rng(5)
    q, qd, qdd = (0.3 * rng.normal(size=(2, 6)) for _ in range(3))
    pid = make_law("pid", ROBOT)
    d_e, d_edot = law_jacobians(pid, np.zeros((2, 6)), q, qd, q, qd, qdd)
    np.testing.assert_allclose(d_e[0], np.diag(pid.kp + pid.ki * pid.period_s), atol=1e-12)
    np.testing.assert_allclose(d_edot[1], np.diag(pid.kd), atol=1e-12)
    smc = make_law("smc", ROBOT)  # central differences of the numpy law as the reference
    d_e, _ = law_jacobians(smc, np.zeros((2, 0)), q, qd, q + 1e-3, qd, qdd)
    h, j = 1e-6, 2
    step = lambda dq: smc.step(np, np.zeros((1, 0)), q[:1] - dq, qd[:1], q[:1] + 1e-3, qd[:1], qdd[:1])[0][0]  # noqa: E731
    unit = np.eye(6)[j][None]
    np.testing.assert_allclose(d_e[0][:, j], (step(h * unit) - step(-h * unit)) / (2 * h), rtol=1e-5, atol=1e-6)


def test_bad_inputs_are_one_line_errors() -> None:
    law = make_law("pd", ROBOT)
    z = np.zeros((2, 6))
    with pytest.raises(ModelInputError):
        evaluate_theorem1(law, ROBOT, z, z, z, z, np.zeros((3, 6)))
    with pytest.raises(ModelInputError):
        evaluate_theorem1(law, ROBOT, z + np.nan, z, z, z, z)
