"""The deployable HMPC (issue 24): W2a on the torque beyond the feed-forward, the smoothness term on
tau_j - tau_{j-1} from the torque applied last cycle, and libfranka's rate bound on the applied torque."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pytest

from models.dynamics import make_dynamics
from models.effort import max_torque_step_nm
from models.errors import ModelInputError
from models.feedback import make_law
from models.hmpc import HMPCConfig, HMPCSolver
from models.hmpc.config import FORMULATIONS
from models.hmpc.result import Rollout, Rows
from models.robots import RobotModel

if TYPE_CHECKING:
    from tests.unit.models.hmpc.conftest import MakeStates


def test_the_rate_bound_holds_on_the_applied_torque(make_states: MakeStates, robot: RobotModel) -> None:
    law = make_law("pd", robot, 1e-3, "stabilized")
    x = make_states(8, seed=5)
    options = {**FORMULATIONS["deployable"], "torque_rate_limit": "none"}
    free = HMPCSolver(law, robot, HMPCConfig(**options)).solve(*x)
    previous = free.tau_nm + 5.0  # 5 N m away on every joint: the free optimum is outside the bound
    bounded = HMPCSolver(law, robot, HMPCConfig(**FORMULATIONS["deployable"])).solve(*x, previous_torque_nm=previous)
    step = np.abs(bounded.tau_nm - previous)
    limit = max_torque_step_nm(robot.torque_rate_nm_s, 1e-3)
    assert np.all(step <= limit + 1e-12)
    assert np.all(step >= 0.99 * limit)  # the bound acts: the optimum lies outside it on every joint
    assert np.all(bounded.status == 0)  # converged, not a fallback


def test_the_smoothness_model_is_the_cost_s_own_derivative(make_states: MakeStates, robot: RobotModel) -> None:
    """The Gauss-Newton gradient of the smoothness term (c dt^2 |M(q)^-1 (tau_j - tau_{j-1})|^2, tau_0 the last
    applied torque) equals central differences of the rolled-out cost, and the term adds to it."""
    law = make_law("pd", robot, 1e-3, "stabilized")
    q, qd, q_d, qd_d, qdd_d = make_states(1, seed=2)
    # no state-bound penalty: it lives in the QP step, not in the normal equations compared here
    config = HMPCConfig(**FORMULATIONS["deployable"], kernels="numpy", use_state_bounds=False)
    solver = HMPCSolver(law, robot, config)
    previous = np.asarray(make_dynamics(robot, "pinocchio").gravity(q), float) + 0.5
    captured: dict[str, Rows] = {}
    rollout = solver._rollout

    def spy(rows: Rows, u: np.ndarray, torque_weight: np.ndarray | None = None) -> Rollout:
        captured.setdefault("rows", rows.take(np.arange(1)))
        return rollout(rows, u, torque_weight)

    solver._rollout = spy  # type: ignore[method-assign]  # capture the rows the solver builds
    solver.solve(q, qd, q_d, qd_d, qdd_d, previous_torque_nm=previous)
    rows = captured["rows"]
    assert rows.previous is not None and rows.rate_weight is not None
    u = np.random.default_rng(1).normal(0.0, 0.01, (1, solver.horizon, robot.n_joints)) + previous[:, None]
    _, gradient, _ = solver._gauss_newton_model(rows, u, solver._rollout(rows, u), np.ones(1))
    h = 1e-4
    numeric = np.empty(u.size)
    for i in range(u.size):
        step = np.zeros(u.size)
        step[i] = h
        up, down = (solver._rollout(rows, u + sign * step.reshape(u.shape)).cost[0] for sign in (1.0, -1.0))
        numeric[i] = (up - down) / (2 * h)
    np.testing.assert_allclose(2.0 * gradient[0], numeric, rtol=1e-4, atol=1e-6 * np.abs(numeric).max())
    without = Rows(rows.q0, rows.qd0, rows.ref_q, rows.ref_qd, rows.qdd_d, rows.law_state, rows.anchor)
    assert solver._rollout(rows, u).cost[0] > solver._rollout(without, u).cost[0]


def test_smoothness_compiled_equals_numpy(make_states: MakeStates, robot: RobotModel) -> None:
    law = make_law("pid", robot, 1e-3, "stabilized")
    x = make_states(6, seed=4)
    previous = np.random.default_rng(0).normal(0.0, 2.0, (6, robot.n_joints))
    taus = [
        HMPCSolver(law, robot, HMPCConfig(**FORMULATIONS["deployable"], kernels=k))
        .solve(*x, previous_torque_nm=previous)
        .tau_nm
        for k in ("numba", "numpy")
    ]
    np.testing.assert_allclose(taus[0], taus[1], atol=1e-6)


def test_a_stiff_feedforward_cost_returns_the_feedforward(make_states: MakeStates, robot: RobotModel) -> None:
    law = make_law("smc", robot, 1e-3, "stabilized")
    q, qd, q_d, qd_d, qdd_d = make_states(5, seed=1)
    result = HMPCSolver(law, robot, HMPCConfig(torque_cost="feedforward", anchor_weight_scale=1e9)).solve(
        q, qd, q_d, qd_d, qdd_d
    )
    feedforward = np.asarray(make_dynamics(robot, "pinocchio").inverse_dynamics(q, qd, qdd_d), float)
    np.testing.assert_allclose(result.tau_nm, feedforward, atol=1e-3 * np.abs(feedforward).max())


@pytest.mark.parametrize(
    ("field", "value"),
    [("torque_rate_limit", "libfranka"), ("rate_weight_scale", -1.0), ("effort_weight_scale", float("nan"))],
)
def test_bad_smoothness_options_are_refused(field: str, value: object) -> None:
    with pytest.raises(ModelInputError, match=f"hmpc config {field}"):
        HMPCConfig(**{field: value})  # type: ignore[arg-type]  # a wrong type on purpose
