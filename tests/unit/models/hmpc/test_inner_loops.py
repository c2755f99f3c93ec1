"""The solver's two inner-loop implementations (numpy, compiled numba) against each other and the
definitions: every method on random inputs, whole solves on random problems, closed loops on the
experiment's conditions. numba is part of the README's test install ([all,test]): these tests need
it and fail, not skip, without it."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from models.conditions import load_conditions
from models.errors import ModelInputError
from models.feedback import LAW_NAMES, make_law
from models.feedback.pd import PDLaw
from models.feedback.pid import PIDLaw
from models.hmpc import HMPCConfig, HMPCSolver, make_hmpc_controller
from models.hmpc.inner_loops import INNER_LOOPS, NumbaInnerLoops, NumpyInnerLoops, make_inner_loops
from models.hmpc.result import CONVERGED
from models.robots import RobotModel
from models.sim import SimConfig, simulate

if TYPE_CHECKING:
    from tests.unit.models.hmpc.conftest import MakeBoxQPs, MakeStates, Objective, States

# What "the same" means between the two. The compiled box QP solves on the free set by Cholesky,
# numpy by LU: round-off differs, the Gauss-Newton stopping test (cost_rtol 1e-4) then stops at
# points that differ along the cost's flat directions (the light wrist joints), so torques agree
# to this, costs much closer. On random problems with ~3 deg errors (bounds active):
RANDOM_TORQUE_ATOL_NM = 1e-4  # measured up to 1.7e-5 N m, of torques up to the 102 N m limit
COST_RTOL = {"absolute": 1e-8, "anchored": 1e-7}  # measured up to 3e-12 and 1.4e-8
# In closed loop the warm-started solves end at the same optimum to far below that:
CLOSED_LOOP_TORQUE_ATOL_NM = 1e-7  # measured up to 4e-10 N m


@pytest.fixture(scope="module")
def loops() -> tuple[NumbaInnerLoops, NumpyInnerLoops]:
    return NumbaInnerLoops(), NumpyInnerLoops()


def test_the_names_choose_the_implementation() -> None:
    assert type(make_inner_loops("numpy")) is NumpyInnerLoops
    assert type(make_inner_loops("numba")) is NumbaInnerLoops
    assert type(make_inner_loops("auto")) is NumbaInnerLoops  # numba is installed here
    assert set(INNER_LOOPS) == {"numpy", "numba"}
    with pytest.raises(ModelInputError, match="hmpc config kernels"):
        make_inner_loops("fortran")


def _block_lower_triangular(rng: np.random.Generator, k: int, horizon: int, rows: int, n: int) -> np.ndarray:
    """(K, T rows, T n) with stage j's rows zero beyond column (j + 1) n, as dE/dU is."""
    f = rng.normal(size=(k, horizon, rows, horizon * n))
    for j in range(horizon):
        f[:, j, :, (j + 1) * n :] = 0.0
    return f.reshape(k, horizon * rows, horizon * n)


@pytest.mark.parametrize("rho", [0.0, 1e6])
def test_stage_cost_same_and_as_defined(loops: tuple[NumbaInnerLoops, NumpyInnerLoops], rho: float) -> None:
    rng = np.random.default_rng(0)
    k, horizon, n, n_features = 9, 5, 6, 14  # two features beyond [e, e_dot]
    features = rng.normal(size=(k, horizon, n_features))
    q_path, qd_path = rng.normal(size=(k, horizon, n)), rng.normal(size=(k, horizon, n))
    deviation = rng.normal(size=(k, horizon, n)) * 50
    feature_weight, torque_weight = rng.uniform(0, 1e4, n_features), rng.uniform(0, 1e-3, n)
    temporal = np.asarray(1 - 0.05 * np.arange(horizon), np.float64)
    limit = np.full(2 * n, 1.2)  # |x| > 1.2 on ~23 % of entries
    fast, slow = (
        impl.stage_cost(features, q_path, qd_path, deviation, feature_weight, torque_weight, temporal, limit, rho)
        for impl in loops
    )
    x = np.concatenate([q_path, qd_path], -1)
    excess = np.maximum(np.abs(x) - limit, 0.0)
    expected = [
        sum(
            temporal[j] * (features[r, j] ** 2 @ feature_weight + deviation[r, j] ** 2 @ torque_weight)
            for j in range(horizon)
        )
        + rho * np.sum(excess[r] ** 2)
        for r in range(k)
    ]
    assert rho == 0 or np.all(excess.sum((1, 2)) > 0)  # the penalty is exercised
    np.testing.assert_allclose(fast, slow, rtol=1e-12)
    np.testing.assert_allclose(slow, expected, rtol=1e-12)


def test_sensitivities_same_and_as_defined(loops: tuple[NumbaInnerLoops, NumpyInnerLoops]) -> None:
    rng = np.random.default_rng(1)
    k, horizon, n, dt = 4, 5, 6, 1e-3
    d_q, d_qd, d_tau = (rng.normal(size=(k, horizon, n, n)) * s for s in (1e3, 1e2, 1e2))
    fast, slow = (impl.sensitivities(d_q, d_qd, d_tau, dt) for impl in loops)
    np.testing.assert_allclose(fast, slow, rtol=1e-12, atol=1e-18)
    # the linearized semi-implicit Euler rollout itself: x_{j+1} = Phi_j x_j + Gamma_j u_j
    u = rng.normal(size=(k, horizon * n))
    q, qd = np.zeros((k, n)), np.zeros((k, n))
    for j in range(horizon):
        u_j = u[:, j * n : (j + 1) * n]
        qd = qd + dt * (np.einsum("kab,kb->ka", d_q[:, j], q) + np.einsum("kab,kb->ka", d_qd[:, j], qd))
        qd = qd + dt * np.einsum("kab,kb->ka", d_tau[:, j], u_j)
        q = q + dt * qd
    np.testing.assert_allclose(np.einsum("kxi,ki->kx", slow, u)[:, -2 * n :], np.concatenate([q, qd], 1), rtol=1e-10)


def test_normal_equations_same_and_as_defined(loops: tuple[NumbaInnerLoops, NumpyInnerLoops]) -> None:
    rng = np.random.default_rng(2)
    k, horizon, n, n_features = 5, 5, 6, 14
    f = _block_lower_triangular(rng, k, horizon, n_features, n)
    weights = rng.uniform(0.5, 2.0, (horizon, n_features))
    residual = rng.normal(size=(k, horizon, n_features))
    deviation, torque_weight = rng.normal(size=(k, horizon * n)), rng.uniform(0.1, 1.0, horizon * n)
    for damping in (0.0, 1e-3):
        levenberg = rng.uniform(1.0, 1e4, k)
        args = (f, weights, residual, deviation, torque_weight, damping, levenberg)
        (h_fast, g_fast), (h_slow, g_slow) = (impl.normal_equations(*args) for impl in loops)
        np.testing.assert_allclose(h_fast, h_slow, rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(g_fast, g_slow, rtol=1e-11, atol=1e-12)
        # the model 1/2 sum w (r + F d)^2 + 1/2 sum W2 (dev + d)^2: gradient and Hessian at d = 0
        w = weights.reshape(-1)
        hessian = np.einsum("kxi,x,kxj->kij", f, w, f) + np.diag(torque_weight)
        gradient = np.einsum("kxi,kx->ki", f, w * residual.reshape(k, -1)) + torque_weight * deviation
        mean = np.einsum("kii->k", hessian) / (horizon * n)
        hessian += np.eye(horizon * n) * (damping * levenberg * mean)[:, None, None]
        np.testing.assert_allclose(h_slow, hessian, rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(g_slow, gradient, rtol=1e-11, atol=1e-12)


@pytest.mark.parametrize("rho", [0.0, 1e6])
def test_model_step_same_with_torque_and_state_bounds_active(
    loops: tuple[NumbaInnerLoops, NumpyInnerLoops], rho: float
) -> None:
    rng = np.random.default_rng(3)
    k, m, nx = 10, 30, 60
    f = rng.normal(size=(k, m, m)) * np.logspace(-2, 1, m)
    hessian0 = f @ np.swapaxes(f, 1, 2) + 1e-3 * np.eye(m)
    gradient0 = rng.normal(size=(k, m)) * 20
    sens = _block_lower_triangular(rng, k, 5, nx // 5, m // 5) * 0.05
    limit = np.full(nx, 1.0)
    x = rng.uniform(-1.3, 1.3, (k, nx))  # some states already beyond their bounds
    lower, upper = -rng.uniform(0.2, 2.0, (k, m)), rng.uniform(0.2, 2.0, (k, m))
    args = (hessian0, gradient0, sens, x, limit, lower, upper, rho, 4, 20, 1e-9)
    (s_fast, p_fast, e_fast), (s_slow, p_slow, e_slow) = (impl.model_step(*args) for impl in loops)
    assert np.any(np.isclose(s_slow, lower) | np.isclose(s_slow, upper))  # torque bounds bind
    np.testing.assert_array_equal(e_fast, e_slow)
    assert e_slow.sum() >= k // 2
    np.testing.assert_allclose(s_fast, s_slow, rtol=0, atol=1e-7 * np.abs(s_slow).max())
    np.testing.assert_allclose(p_fast, p_slow, rtol=1e-8)
    assert np.all((s_fast >= lower - 1e-12) & (s_fast <= upper + 1e-12))
    assert np.all(p_slow >= 0)  # a step never predicts an increase (d = 0 is feasible)


def test_compiled_box_qp_matches_numpy(
    loops: tuple[NumbaInnerLoops, NumpyInnerLoops], make_box_qps: MakeBoxQPs, objective: Objective
) -> None:
    hessian, gradient, lower, upper = make_box_qps(seed=2, rows=16)
    (x_nb, ok_nb), (x_np, ok_np) = (impl.box_qp(hessian, gradient, lower, upper, 20, 1e-9) for impl in loops)
    assert ok_np.all() and ok_nb.all()
    assert np.all((x_nb >= lower) & (x_nb <= upper))
    np.testing.assert_allclose(
        objective(hessian, gradient, x_nb), objective(hessian, gradient, x_np), rtol=1e-9, atol=1e-12
    )


def _both(law: Any, robot: RobotModel, args: States, **options: Any) -> list[Any]:
    state = law.initial_state(args[0])
    return [
        HMPCSolver(law, robot, HMPCConfig(kernels=kernels, **options)).solve(*args, state)
        for kernels in ("numba", "numpy")
    ]


def _assert_same_solve(fast: Any, slow: Any, torque_cost: str = "absolute") -> None:
    np.testing.assert_array_equal(fast.status, slow.status)
    np.testing.assert_array_equal(fast.iterations, slow.iterations)
    np.testing.assert_allclose(fast.cost, slow.cost, rtol=COST_RTOL[torque_cost])
    np.testing.assert_allclose(fast.candidate_cost, slow.candidate_cost, rtol=1e-12)
    np.testing.assert_allclose(fast.tau_nm, slow.tau_nm, rtol=0, atol=RANDOM_TORQUE_ATOL_NM)


# Every law but H-infinity, whose gain synthesis alone takes ~10 s here: a law enters the inner loops
# only through its torque (the candidates' seed) and its state.
@pytest.mark.parametrize("torque_cost", ["absolute", "anchored"])
@pytest.mark.parametrize("law_name", [name for name in LAW_NAMES if name != "hinf"])
def test_every_law_same_solve_on_random_problems(
    robot: RobotModel, make_states: MakeStates, law_name: str, torque_cost: str
) -> None:
    # ~3 deg errors: the torque box binds and most rows need several Gauss-Newton iterations
    args = make_states(12, seed=21, error_rad=0.05)
    law = make_law(law_name, robot, 1e-3)
    fast, slow = _both(law, robot, args, torque_cost=torque_cost, on_budget_exhausted="best_iterate")
    assert fast.iterations.max() >= 2
    assert np.any(np.isclose(np.abs(slow.sequence_nm), robot.torque_limit_nm))
    _assert_same_solve(fast, slow, torque_cost)


def test_compiled_kernels_reach_the_numpy_optimum(robot: RobotModel, make_states: MakeStates) -> None:
    # Large errors (torque box and velocity penalty active, several Gauss-Newton iterations):
    # the compiled inner loops take the same path as the numpy ones, to round-off.
    law = PDLaw(robot.n_joints, 1e-3, robot.torque_limit_nm)  # the paper's gains
    args = make_states(12, seed=12, error_rad=0.08)
    fast, slow = _both(law, robot, args, on_budget_exhausted="best_iterate")
    assert fast.iterations.max() >= 2
    _assert_same_solve(fast, slow)


class _SlidingSurfacePID(PIDLaw):
    """PID whose MPC error vector adds a sliding surface with its integral state:
    E = [e, e_dot, e_dot + 20 e + xi] (it depends on the predicted state and on the law's)."""

    name = "pid_sliding_surface"

    def error_features(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any) -> Any:
        e, e_dot = q_d - q, qd_d - qd
        return xp.concatenate([e, e_dot, e_dot + 20.0 * e + state], -1)


def test_a_laws_own_features_same_solve_and_reduce_to_the_base_ones(robot: RobotModel, make_states: MakeStates) -> None:
    law = _SlidingSurfacePID(robot.n_joints, 1e-3, robot.torque_limit_nm)
    args = make_states(8, seed=4, error_rad=0.03)
    # weighted: the integral term changes the optimum; both implementations find the same one
    fast, slow = _both(law, robot, args, extra_feature_weight=1e3)
    assert np.all(slow.status == CONVERGED) and np.all(slow.cost <= slow.candidate_cost)
    _assert_same_solve(fast, slow)
    # unweighted: E's first 2N entries are [e, e_dot], so the optimum is the base law's (PID's), reached
    # through the features' Jacobian (central differences) instead of dE/dx = -I
    base = _both(PIDLaw(robot.n_joints, 1e-3, robot.torque_limit_nm), robot, args)
    unweighted = _both(law, robot, args)
    for own, plain in zip(unweighted, base, strict=True):
        np.testing.assert_array_equal(own.iterations, plain.iterations)
        np.testing.assert_allclose(own.cost, plain.cost, rtol=1e-10)  # measured 2e-14
        np.testing.assert_allclose(own.tau_nm, plain.tau_nm, rtol=0, atol=1e-6)  # measured 2e-8 N m
    assert np.abs(fast.tau_nm - base[0].tau_nm).max() > 100 * RANDOM_TORQUE_ATOL_NM  # the weight matters


@pytest.mark.parametrize(("law_name", "torque_cost"), [("pd", "absolute"), ("smc", "absolute"), ("pd", "anchored")])
def test_same_closed_loop_on_the_experiments_conditions(robot: RobotModel, law_name: str, torque_cost: str) -> None:
    # The paper's five conditions (C4/C5 start off the reference), shortened to 0.3 s with the
    # impulse moved to t = 0.1 s; the HMPC controller as `hil experiment --modes hmpc` runs it.
    conditions = [
        replace(c, duration_s=0.3, disturbance=replace(c.disturbance, time_s=0.1)) for c in load_conditions(robot=robot)
    ]
    runs = []
    law = make_law(law_name, robot, 1e-3)  # stateless: its state lives in each controller
    for kernels in ("numba", "numpy"):
        controller = make_hmpc_controller(law, robot, kernels=kernels, torque_cost=torque_cost)
        runs.append((simulate(robot, controller, conditions, SimConfig()), controller))
    (fast, fast_controller), (slow, slow_controller) = runs
    assert fast.within_limits.all() and slow.within_limits.all()
    assert fast_controller.fallback_count == slow_controller.fallback_count == 0
    assert fast_controller.iterations == slow_controller.iterations
    np.testing.assert_allclose(fast.tau, slow.tau, rtol=0, atol=CLOSED_LOOP_TORQUE_ATOL_NM)
