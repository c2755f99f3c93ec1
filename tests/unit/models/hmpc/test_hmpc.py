"""HMPC: optimizer quality, bounds, dynamics backends agree, fallbacks, batch == single, bad config.

numpy == compiled inner loops: test_inner_loops.py."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from models.errors import ModelInputError
from models.executors import LocalProcessExecutor
from models.feedback.pd import PDLaw
from models.hmpc import HMPCConfig, HMPCSolver, make_hmpc_controller, solve_batch
from models.hmpc.boxqp import solve_box_qp
from models.hmpc.result import CONVERGED, NONFINITE_INPUT, NOT_CONVERGED
from models.robots import RobotModel

if TYPE_CHECKING:
    from tests.unit.models.hmpc.conftest import MakeBoxQPs, MakeStates, Objective


@pytest.fixture(scope="module")
def law(robot: RobotModel) -> PDLaw:
    return PDLaw(robot.n_joints, 1e-3, robot.torque_limit_nm)


def test_refined_cost_below_best_candidate(make_states: MakeStates, law: PDLaw, robot: RobotModel) -> None:
    result = HMPCSolver(law, robot).solve(*make_states(16))
    assert np.all(result.status == CONVERGED)
    # the refinement must actually improve on the paper's candidates, not just pick one
    assert np.all(result.cost <= result.candidate_cost)
    assert np.median(result.cost / result.candidate_cost) < 0.9
    assert np.all(result.iterations >= 1)


def test_solution_is_a_local_minimum(make_states: MakeStates, law: PDLaw, robot: RobotModel) -> None:
    solver = HMPCSolver(law, robot)
    args = make_states(1, seed=3)
    result = solver.solve(*args)
    from models.hmpc.result import Rows

    ref_q, ref_qd = solver.reference_preview(*args[2:])
    rows = Rows(args[0], args[1], ref_q, ref_qd, args[4], np.zeros((1, 0)))
    best = result.sequence_nm
    base = solver._rollout(rows, best).cost[0]
    rng = np.random.default_rng(1)
    for _ in range(20):  # no small perturbation of the whole sequence does better
        trial = best + rng.normal(0.0, 1e-3, best.shape)
        assert solver._rollout(rows, trial).cost[0] >= base * (1 - 1e-6)


def test_torque_bounds_respected_and_active(make_states: MakeStates, law: PDLaw, robot: RobotModel) -> None:
    tight = (5.0, 5.0, 3.0, 1.0, 1.0, 1.0)
    solver = HMPCSolver(law, robot, HMPCConfig(torque_limit_nm=tight, max_iterations=10))
    q, qd, q_d, qd_d, qdd_d = make_states(8, seed=2, error_rad=0.05)
    result = solver.solve(q, qd, q_d, qd_d, qdd_d)
    limit = np.array(tight)
    assert np.all(np.abs(result.sequence_nm) <= limit + 1e-9)
    assert np.all(np.abs(result.tau_nm) <= limit + 1e-9)
    assert np.any(np.isclose(np.abs(result.sequence_nm), limit))  # the bounds do bind here


def test_velocity_bound_holds_on_prediction(make_states: MakeStates, law: PDLaw, robot: RobotModel) -> None:
    # A large position error pulls the joints hard; the predicted velocity must stay within 0.3 rad/s.
    limit = 0.3
    solver = HMPCSolver(law, robot, HMPCConfig(velocity_limit_rad_s=(limit,) * 6, max_iterations=10))
    q, qd, q_d, qd_d, qdd_d = make_states(4, seed=4, error_rad=0.1)
    qd, qd_d, qdd_d = np.zeros_like(qd), np.zeros_like(qd_d), np.zeros_like(qdd_d)
    result = solver.solve(q, qd, q_d, qd_d, qdd_d)
    from models.hmpc.result import Rows

    ref_q, ref_qd = solver.reference_preview(q_d, qd_d, qdd_d)
    rollout = solver._rollout(Rows(q, qd, ref_q, ref_qd, qdd_d, np.zeros((4, 0))), result.sequence_nm)
    unconstrained = HMPCSolver(law, robot, HMPCConfig(use_state_bounds=False, max_iterations=10)).solve(
        q, qd, q_d, qd_d, qdd_d
    )
    rollout_free = solver._rollout(Rows(q, qd, ref_q, ref_qd, qdd_d, np.zeros((4, 0))), unconstrained.sequence_nm)
    assert np.abs(rollout_free.qd).max() > 1.5 * limit  # without the bound the optimizer would exceed it
    assert np.abs(rollout.qd).max() <= limit * 1.01  # soft bound: stiff penalty, 1 % slack


@pytest.mark.parametrize("law_name", ["pd", "pid"])
def test_rne_and_pinocchio_backends_agree(make_states: MakeStates, robot: RobotModel, law_name: str) -> None:
    from models.feedback import make_law

    law = make_law(law_name, robot, 1e-3)
    args = make_states(6, seed=5)
    state = law.initial_state(args[0])
    fast = HMPCSolver(law, robot, HMPCConfig(backend="pinocchio")).solve(*args, state)
    own = HMPCSolver(law, robot, HMPCConfig(backend="rne")).solve(*args, state)
    assert np.array_equal(fast.status, own.status)
    np.testing.assert_allclose(own.tau_nm, fast.tau_nm, rtol=0, atol=1e-8)
    np.testing.assert_allclose(own.sequence_nm, fast.sequence_nm, rtol=0, atol=1e-8)


def test_nan_state_falls_back_and_never_outputs_nan(make_states: MakeStates, law: PDLaw, robot: RobotModel) -> None:
    q, qd, q_d, qd_d, qdd_d = make_states(3, seed=6)
    q[1, 2] = np.nan
    qd_d[2, 0] = np.inf
    hold = np.full((3, 6), 0.5)
    result = HMPCSolver(law, robot).solve(q, qd, q_d, qd_d, qdd_d, hold_torque_nm=hold)
    assert list(result.status) == [CONVERGED, NONFINITE_INPUT, NONFINITE_INPUT]
    assert np.all(np.isfinite(result.tau_nm))
    assert list(result.fell_back) == [False, True, True]
    np.testing.assert_array_equal(result.tau_nm[1], hold[1])  # PD's torque is NaN there too
    np.testing.assert_array_equal(result.tau_nm[2], result.tau_fb_nm[2])  # finite (saturated) law torque


def test_controller_counts_fallbacks_and_times_cycles(make_states: MakeStates, law: PDLaw, robot: RobotModel) -> None:
    controller = make_hmpc_controller(law, robot)
    q, qd, q_d, qd_d, qdd_d = make_states(2, seed=7)
    controller.reset(q)
    controller(0.0, q, qd, q_d, qd_d, qdd_d)
    q_bad = q.copy()
    q_bad[0, 0] = np.nan
    tau = controller(0.001, q_bad, qd, q_d, qd_d, qdd_d)
    assert np.all(np.isfinite(tau))
    assert controller.fallback_count == 1 and controller.fallbacks["nonfinite_input"] == 1
    assert len(controller.cycle_times_s) == 2 and all(t > 0 for t in controller.cycle_times_s)


def test_budget_exhausted_falls_back_to_feedback(make_states: MakeStates, law: PDLaw, robot: RobotModel) -> None:
    # one Gauss-Newton iteration with a strict tolerance cannot converge on large errors
    config = HMPCConfig(max_iterations=1, cost_rtol=1e-14, cost_atol=0.0)
    args = make_states(4, seed=8, error_rad=0.1)
    result = HMPCSolver(law, robot, config).solve(*args)
    assert np.all(result.status == NOT_CONVERGED)
    np.testing.assert_array_equal(result.tau_nm, result.tau_fb_nm)
    kept = HMPCSolver(
        law, robot, HMPCConfig(max_iterations=1, cost_rtol=1e-14, cost_atol=0.0, on_budget_exhausted="best_iterate")
    ).solve(*args)
    np.testing.assert_array_equal(kept.tau_nm, kept.sequence_nm[:, 0])


def test_warm_start_reaches_the_same_optimum_in_fewer_iterations(
    make_states: MakeStates, law: PDLaw, robot: RobotModel
) -> None:
    solver = HMPCSolver(law, robot)
    args = make_states(8, seed=9)
    cold = solver.solve(*args)
    warm_guess = np.concatenate([cold.sequence_nm[:, :1], cold.sequence_nm[:, :-1]], 1)  # undone shift
    warm = solver.solve(*args, warm_start_nm=warm_guess)
    assert warm.iterations.sum() <= cold.iterations.sum() + len(warm.iterations)
    # the same optimum to the solver's tolerance (cost_rtol = 1e-4); the cost is flat along the
    # light wrist joints, so compare costs, not torques
    np.testing.assert_allclose(warm.cost, cold.cost, rtol=2e-4)


def test_batch_equals_single(make_states: MakeStates, law: PDLaw, robot: RobotModel) -> None:
    args = make_states(10, seed=10, error_rad=0.05)
    tau, status = solve_batch(law, robot, *args, chunk_states=4)
    solver = HMPCSolver(law, robot)
    for b in range(10):
        one = solver.solve(*(a[b : b + 1] for a in args))
        assert status[b] == one.status[0]
        np.testing.assert_allclose(tau[b], one.tau_nm[0], rtol=0, atol=1e-9)


def test_process_pool_equals_serial(make_states: MakeStates, law: PDLaw, robot: RobotModel) -> None:
    args = make_states(12, seed=11)
    serial, _ = solve_batch(law, robot, *args, chunk_states=5)
    with LocalProcessExecutor(2) as executor:
        parallel, _ = solve_batch(law, robot, *args, chunk_states=5, executor=executor)
    np.testing.assert_array_equal(parallel, serial)


@pytest.mark.parametrize(
    "options",
    [
        {"horizon_steps": 0},
        {"position_error_weight": math.nan},
        {"torque_weight": -1.0},
        {"candidate_scales": ()},
        {"torque_limit_nm": (10.0, 10.0, 10.0, -1.0, 10.0, 10.0)},
        {"velocity_limit_rad_s": (math.nan,) * 6},
        {"temporal_decay": 0.3},  # the 5th temporal weight would be negative
        {"prediction_step_s": 0.0},
        {"max_iterations": 0},
        {"backend": "matlab"},
        {"kernels": "fortran"},
        {"no_such_option": 1},
    ],
)
def test_bad_configuration_is_a_model_input_error(law: PDLaw, robot: RobotModel, options: dict[str, Any]) -> None:
    with pytest.raises(ModelInputError) as info:
        make_hmpc_controller(law, robot, **options)
    assert info.value.exit_code == 2


def test_wrong_joint_count_weights_rejected(law: PDLaw, robot: RobotModel) -> None:
    with pytest.raises(ModelInputError, match="position_error_weight"):
        HMPCSolver(law, robot, HMPCConfig(position_error_weight=(1.0, 2.0)))


def test_box_qp_matches_a_reference_solver(make_box_qps: MakeBoxQPs) -> None:
    from scipy.optimize import Bounds, minimize

    hessian, gradient, lower, upper = make_box_qps(seed=1, unit_lower=True)
    k, n = gradient.shape
    x, converged = solve_box_qp(hessian, gradient, lower, upper, 20)
    assert converged.all()
    assert np.all((x >= lower) & (x <= upper))
    for row in range(k):

        def f(z: np.ndarray, r: int = row) -> float:
            return float(gradient[r] @ z + 0.5 * z @ hessian[r] @ z)

        ref = minimize(
            f,
            np.zeros(n),
            jac=lambda z, r=row: gradient[r] + hessian[r] @ z,
            bounds=Bounds(lower[row], upper[row]),
            method="L-BFGS-B",
            options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10000},
        )
        assert f(x[row]) <= ref.fun + 1e-9


def test_warm_started_box_qp_reaches_the_same_minimizer(make_box_qps: MakeBoxQPs, objective: Objective) -> None:
    # A guess only picks the first active set: from the solution itself, from a wrong set of
    # bounds, or from none, the minimizer (unique: H positive definite) is the same.
    hessian, gradient, lower, upper = make_box_qps(seed=3)
    k, n = gradient.shape
    rng = np.random.default_rng(4)
    cold, ok = solve_box_qp(hessian, gradient, lower, upper, 20)
    assert ok.all()
    wrong = np.where(rng.random((k, n)) < 0.3, np.where(rng.random((k, n)) < 0.5, lower, upper), 0.0)
    for guess in (cold, wrong, np.zeros((k, n))):
        warm, ok = solve_box_qp(hessian, gradient, lower, upper, 20, guess=guess)
        assert ok.all() and np.all((warm >= lower) & (warm <= upper))
        np.testing.assert_allclose(
            objective(hessian, gradient, warm), objective(hessian, gradient, cold), rtol=1e-9, atol=1e-12
        )
