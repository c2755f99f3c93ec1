"""The six feedback laws: registry, finiteness, saturation, batching, numpy == torch, documented state."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from models.dynamics import make_dynamics
from models.errors import ModelInputError
from models.feedback import LAW_NAMES, ROBOT_GAINS, make_law
from models.feedback.adrc import ADRCLaw
from models.feedback.hinf import makeweight_coefficients
from models.robots import load_robot

ROBOT = load_robot("ur5_paper")
LAWS = {name: make_law(name, ROBOT) for name in LAW_NAMES}


def _signals(rng: np.random.Generator, batch: int, scale: float = 1.0) -> list[np.ndarray]:
    return [scale * rng.normal(size=(batch, 6)) for _ in range(5)]


def _state(law, rng, q):
    return law.initial_state(q) + 0.01 * rng.normal(size=(len(q), law.state_size))


def test_registry_rejects_unknown_law_and_wrong_joint_count() -> None:
    with pytest.raises(ModelInputError, match="unknown 'lqr'"):
        make_law("lqr", ROBOT)
    panda = load_robot("panda")
    for name in ("pd", "pid", "adrc", "smc", "mrac"):
        with pytest.raises(ModelInputError, match="7"):
            make_law(name, panda)
    assert make_law("pd", panda, kp=np.ones(7), kd=0.1).n_joints == 7
    with pytest.raises(ModelInputError):
        make_law("pd", ROBOT, kp=[1.0, 2.0])


@pytest.mark.parametrize("name", LAW_NAMES)
def test_gain_sets_refuse_another_robot(name: str) -> None:
    """The real UR5 has six joints too: the paper's UR5 gains must not reach it silently."""
    ur5 = load_robot("ur5")
    for gain_set in ("paper", "stabilized"):  # 'designed' is any robot's (tests/unit/models/feedback/test_design.py)
        with pytest.raises(ModelInputError, match=f"gain set '{gain_set}'.*robot 'ur5' \\(6 joints\\); pass"):
            make_law(name, ur5, gain_set=gain_set)
    # every gain given: the caller's own set
    own: dict[str, np.ndarray | float] = {gain: np.ones(6) for gain in ROBOT_GAINS[name]}
    if name == "adrc":
        own.update(omega_o=50.0, omega_c=10.0)
    if name in ("hinf", "smc"):
        own = {g: (0.5 if g in ("alpha", "epsilon") else v) for g, v in own.items()}
    assert make_law(name, ur5, **own).n_joints == 6


@pytest.mark.parametrize("name", LAW_NAMES)
def test_step_is_finite_saturated_and_rowwise(name: str) -> None:
    law, rng = LAWS[name], np.random.default_rng(0)
    q, qd, q_d, qd_d, qdd_d = _signals(rng, 5)
    state = _state(law, rng, q)
    tau, next_state = law.step(np, state, q, qd, q_d, qd_d, qdd_d)
    assert tau.shape == (5, 6) and next_state.shape == (5, law.state_size)
    assert np.all(np.isfinite(tau)) and np.all(np.isfinite(next_state))
    for b in range(5):  # batch == one row at a time
        tau_b, state_b = law.step(
            np, state[b : b + 1], q[b : b + 1], qd[b : b + 1], q_d[b : b + 1], qd_d[b : b + 1], qdd_d[b : b + 1]
        )
        np.testing.assert_allclose(tau_b[0], tau[b], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(state_b[0], next_state[b], rtol=1e-12, atol=1e-12)
    # Huge errors: every torque saturates at the limit, still finite.
    big = [1e3 * a for a in (q, qd)]
    tau_big, state_big = law.step(np, state, big[0], big[1], q_d, qd_d, qdd_d)
    assert np.all(np.isfinite(tau_big)) and np.all(np.isfinite(state_big))
    assert np.all(np.abs(tau_big) <= ROBOT.torque_limit_nm + 1e-12)
    assert np.isclose(np.abs(tau_big), ROBOT.torque_limit_nm).any()


@pytest.mark.parametrize("name", LAW_NAMES)
def test_numpy_and_torch_steps_agree(name: str) -> None:
    law, rng = LAWS[name], np.random.default_rng(1)
    signals = _signals(rng, 4)
    state = _state(law, rng, signals[0])
    tau, next_state = law.step(np, state, *signals)
    as_t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    tau_t, next_t = law.step(torch, as_t(state), *map(as_t, signals))
    np.testing.assert_allclose(tau_t.numpy(), tau, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(next_t.numpy(), next_state, rtol=1e-10, atol=1e-10)


def test_pid_integrator_accumulates_error_and_is_clamped() -> None:
    law = LAWS["pid"]
    q, e = np.zeros((1, 6)), np.full((1, 6), 0.1)
    state = law.initial_state(q)
    for _ in range(10):
        tau, state = law.step(np, state, q, q, q + e, q, q)
    np.testing.assert_allclose(state, 10 * law.period_s * e)
    np.testing.assert_allclose(tau, law.kp * e + law.ki * state)
    _, state = law.step(np, np.full((1, 6), 1e9), q, q, q + e, q, q)
    np.testing.assert_allclose(state[0], law.integral_limit_rad_s)


def test_adrc_eso_estimates_a_constant_disturbance_on_a_double_integrator() -> None:
    # One joint, inertia m = b0: m q_ddot = tau + d. The ESO's z3 must converge to d / b0.
    b0, d_nm, dt = 0.1, 0.5, 1e-3
    law = ADRCLaw(1, dt, np.array([100.0]), b0=np.array([b0]))
    q, qd = np.zeros((1, 1)), np.zeros((1, 1))
    state = law.initial_state(q)
    ref = np.full((1, 1), 0.2)
    for _ in range(2000):
        tau, state = law.step(np, state, q, qd, ref, 0 * ref, 0 * ref)
        acc = (tau + d_nm) / b0  # exact ZOH step of the double integrator
        q, qd = q + qd * dt + 0.5 * acc * dt**2, qd + acc * dt
    assert state[0, 2] == pytest.approx(d_nm / b0, rel=1e-3)
    assert q[0, 0] == pytest.approx(0.2, abs=1e-4)
    np.testing.assert_allclose(state[:, law.applied_torque_slice], tau)  # the applied torque is kept


def test_adrc_uses_the_applied_torque_written_into_its_state() -> None:
    law, q = LAWS["adrc"], np.full((1, 6), 0.1)
    state = law.initial_state(q)
    _, a = law.step(np, law.with_applied_torque(state, np.zeros((1, 6))), q, q, q, q, q)
    _, b = law.step(np, law.with_applied_torque(state, np.ones((1, 6))), q, q, q, q, q)
    assert not np.allclose(a[:, :18], b[:, :18])


def test_makeweight_matches_matlab_definition() -> None:
    for dc, wc, hf in ((10, 1, 0.01), (0.1, 1, 10), (100, 3, 0.5)):
        num, den = makeweight_coefficients(dc, wc, hf)
        w = lambda s: np.polyval(num, s) / np.polyval(den, s)  # noqa: E731
        assert abs(w(0)) == pytest.approx(dc) and abs(w(1j * wc)) == pytest.approx(1.0)
        assert abs(w(1e9j)) == pytest.approx(hf, rel=1e-6)
    with pytest.raises(ModelInputError):
        makeweight_coefficients(0.5, 1, 0.1)


def test_hinf_synthesis_reports_finite_gamma_and_a_stable_discrete_controller() -> None:
    law = LAWS["hinf"]
    gammas = np.array(law.params["gamma"])
    assert gammas.shape == (6,) and np.all(np.isfinite(gammas)) and np.all(gammas > 0)
    assert np.max(np.abs(np.linalg.eigvals(law.ad))) < 1.0
    # Zero error and zero controller state: the law outputs the nominal gravity only.
    q = np.array([[0.1, 0.7, -0.4, 0.3, 0.2, 0.1]])
    tau, _ = law.step(np, np.zeros((1, law.state_size)), q, 0 * q, q, 0 * q, 0 * q)
    np.testing.assert_allclose(tau[0], make_dynamics(ROBOT).gravity(q[0]), atol=1e-12)


def test_smc_is_computed_torque_on_the_surface() -> None:
    law, rng = LAWS["smc"], np.random.default_rng(2)
    q, qd, qdd = (0.5 * rng.normal(size=(1, 6)) for _ in range(3))
    tau, _ = law.step(np, np.zeros((1, 0)), q, qd, q, qd, qdd)  # e = e_dot = 0 -> s = 0
    np.testing.assert_allclose(tau[0], make_dynamics(ROBOT).inverse_dynamics(q[0], qd[0], qdd[0]), atol=1e-10)


def test_mrac_adapts_along_the_gradient_and_stays_in_its_box() -> None:
    law, n = LAWS["mrac"], 6
    q, e = np.zeros((1, n)), np.full((1, n), 0.01)
    theta0 = law.initial_state(q)
    _, theta = law.step(np, theta0, q, q, q + e, q, q)  # qdd_r = 0, qd_r = Lambda e, s = Lambda e
    s = law.lam * e[0]
    np.testing.assert_allclose(theta[0, n : 2 * n] - theta0[0, n : 2 * n], law.period_s * law.gamma * s * s)
    np.testing.assert_allclose(theta[0, 2 * n :], law.period_s * law.gamma * s)
    _, theta = law.step(np, theta0, q, q, q + 1e6, q, q)
    assert np.all(theta <= law.theta_max) and np.all(theta >= law.theta_min)


def _rk4_hold(law, q_ref: np.ndarray, q0: np.ndarray, periods: int) -> np.ndarray:
    """Closed loop on ur5_paper: zero-order hold over each period, one RK4 step per period."""
    dyn, dt = make_dynamics(ROBOT, "pinocchio"), law.period_s
    q, qd = q0[None].copy(), np.zeros((1, 6))
    state, zero = law.initial_state(q), np.zeros((1, 6))
    errors = []
    for _ in range(periods):
        tau, state = law.step(np, state, q, qd, q_ref[None], zero, zero)
        f = lambda x, v: (v, dyn.forward_dynamics(x, v, tau))  # noqa: E731
        k1 = f(q, qd)
        k2 = f(q + 0.5 * dt * k1[0], qd + 0.5 * dt * k1[1])
        k3 = f(q + 0.5 * dt * k2[0], qd + 0.5 * dt * k2[1])
        k4 = f(q + dt * k3[0], qd + dt * k3[1])
        q = q + dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        qd = qd + dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        errors.append(np.abs(q_ref - q[0]).max())
    return np.array(errors)


@pytest.mark.parametrize("name", LAW_NAMES)
def test_closed_loop_holding_a_constant_reference_stays_finite_and_close(name: str) -> None:
    q_ref = np.array([0.3, 0.4, -0.3, 0.2, 0.3, 0.2])
    errors = _rk4_hold(LAWS[name], q_ref, q_ref - 0.02, periods=300)
    assert np.all(np.isfinite(errors))
    assert errors.max() < 0.3  # rad; a diverging loop leaves this within 0.3 s
