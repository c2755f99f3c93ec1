"""The HMPC solver's inner loops behind one interface, in numpy or compiled (numba), chosen once.

``HMPCSolver`` runs one algorithm (docs/hmpc.md, "The solver"); the array work inside a
Gauss-Newton iteration is delegated to an ``InnerLoops`` object picked when the solver is built
(``HMPCConfig.kernels``):

- ``stage_cost``: the cost J of predicted paths, given their error features;
- ``sensitivities``: S = dx/dU of the linearized rollout;
- ``normal_equations``: H, g of the Gauss-Newton model from the features' sensitivities;
- ``model_step``: the box QP over the torque box, with the state-bound penalty's active set
  iterated around it;
- ``box_qp``: that QP alone (a batch of them).

``NumpyInnerLoops`` vectorizes each over the batch; ``NumbaInnerLoops`` runs the same algorithms
row by row in compiled code (``models.hmpc.kernels``). Same results to round-off:
tests/unit/models/hmpc/test_inner_loops.py checks every method and whole solves against each other.
Names map to classes in ``INNER_LOOPS`` (like python-can's interface table); ``auto`` takes numba
when it is installed.
"""

from __future__ import annotations

import importlib.util
from typing import Protocol

import numpy as np

from models.errors import ModelInputError
from models.hmpc.boxqp import solve_box_qp


class InnerLoops(Protocol):
    """The array work of one Gauss-Newton iteration, for K independent rows.

    Shapes: T preview steps, N joints, nE error features (>= 2N, the first 2N are [e, e_dot]),
    M = T N torques, X = T 2N predicted states.
    """

    name: str
    #: True when the first call compiles or loads code: the solver then solves once at rest when it
    #: is built, so the first control cycle does not pay for it.
    needs_warm_up: bool

    def stage_cost(
        self,
        features: np.ndarray,
        q_path: np.ndarray,
        qd_path: np.ndarray,
        deviation: np.ndarray,
        feature_weight: np.ndarray,
        torque_weight: np.ndarray,
        temporal: np.ndarray,
        state_limit: np.ndarray,
        rho: float,
    ) -> np.ndarray:
        """J (K,) = sum_j w_j [E_j' W1 E_j + dev_j' W2 dev_j] + rho |x - clip(x, -limit, limit)|^2, for
        features E (K, T, nE), predicted q, qd (K, T, N), what W2 weighs (K, T, N), W1 (nE,),
        W2 (N,), temporal weights w (T,), state_limit (2N,)."""
        ...

    def sensitivities(self, d_q: np.ndarray, d_qd: np.ndarray, d_tau: np.ndarray, dt: float) -> np.ndarray:
        """S = dx/dU (K, X, M) of the semi-implicit Euler rollout linearized at U, from the per-step
        derivatives dqdd/dq, dqdd/dqd, dqdd/dtau (K, T, N, N) and the prediction step dt (s)."""
        ...

    def normal_equations(
        self,
        feature_sens: np.ndarray,
        weights: np.ndarray,
        residual: np.ndarray,
        deviation: np.ndarray,
        torque_weight: np.ndarray,
        damping: float,
        levenberg: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """H (K, M, M), g (K, M) of 1/2 sum w (r + F d)^2 + 1/2 sum W2 (dev + d)^2 in the step d, with
        F (K, T nE, M) block lower triangular, stage weights w (T, nE), r (K, T, nE), dev (K, M),
        W2 (M,); H's diagonal raised by damping * levenberg (K,) * its mean (Levenberg-Marquardt)."""
        ...

    def model_step(
        self,
        hessian0: np.ndarray,
        gradient0: np.ndarray,
        sens: np.ndarray,
        x: np.ndarray,
        limit: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        rho: float,
        rounds: int,
        max_qp_iterations: int,
        qp_tolerance: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The step d (K, M) minimizing the model g'd + 1/2 d'Hd + 1/2 rho |viol(x + S d)|^2 within
        lower <= d <= upper (K, M), the decrease of J it predicts (K,), and whether d is the model's
        exact minimizer (K,) bool (QP converged, penalty set settled within ``rounds``); x (K, X) the
        predicted states, limit (X,) their bounds."""
        ...

    def box_qp(
        self,
        hessian: np.ndarray,
        gradient: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        max_iterations: int,
        tolerance: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(x (K, M), converged (K,)): min g'x + 1/2 x'Hx within lower <= x <= upper, per row."""
        ...


def _penalty(y: np.ndarray, limit: np.ndarray, rho: float) -> np.ndarray:
    violation = y - np.clip(y, -limit, limit)
    value: np.ndarray = 0.5 * rho * np.einsum("kx,kx->k", violation, violation)
    return value


class NumpyInnerLoops:
    """Vectorized over the batch: every row takes part in every array operation."""

    name = "numpy"
    needs_warm_up = False

    def stage_cost(
        self,
        features: np.ndarray,
        q_path: np.ndarray,
        qd_path: np.ndarray,
        deviation: np.ndarray,
        feature_weight: np.ndarray,
        torque_weight: np.ndarray,
        temporal: np.ndarray,
        state_limit: np.ndarray,
        rho: float,
    ) -> np.ndarray:
        stage = np.einsum("ktf,f->kt", features * features, feature_weight)
        stage = stage + np.einsum("ktn,n->kt", deviation * deviation, torque_weight)
        cost: np.ndarray = stage @ temporal
        if rho > 0:
            x = np.concatenate([q_path, qd_path], -1)
            violation = x - np.clip(x, -state_limit, state_limit)
            cost = cost + rho * np.einsum("ktx,ktx->k", violation, violation)
        return cost

    def sensitivities(self, d_q: np.ndarray, d_qd: np.ndarray, d_tau: np.ndarray, dt: float) -> np.ndarray:
        k, horizon, n = d_q.shape[:3]
        eye = np.eye(n)
        # x+ = Phi x + Gamma u (linearized semi-implicit Euler), x = (q, qd)
        phi = np.empty((k, horizon, 2 * n, 2 * n))
        velocity_block = eye + dt * d_qd
        phi[:, :, :n, :n] = eye + dt * dt * d_q
        phi[:, :, :n, n:] = dt * velocity_block
        phi[:, :, n:, :n] = dt * d_q
        phi[:, :, n:, n:] = velocity_block
        gamma = np.concatenate([dt * dt * d_tau, dt * d_tau], 2)  # (K, T, 2N, N)
        sens = np.zeros((k, horizon, 2 * n, horizon * n))  # d x_{k+j} / d U
        sens[:, 0, :, :n] = gamma[:, 0]
        for j in range(1, horizon):
            sens[:, j, :, : j * n] = phi[:, j] @ sens[:, j - 1, :, : j * n]
            sens[:, j, :, j * n : (j + 1) * n] = gamma[:, j]
        return sens.reshape(k, horizon * 2 * n, horizon * n)

    def normal_equations(
        self,
        feature_sens: np.ndarray,
        weights: np.ndarray,
        residual: np.ndarray,
        deviation: np.ndarray,
        torque_weight: np.ndarray,
        damping: float,
        levenberg: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        k, m = feature_sens.shape[0], feature_sens.shape[2]
        w = weights.reshape(-1)  # (T nE,)
        hessian = np.swapaxes(feature_sens, 1, 2) @ (feature_sens * w[:, None])
        gradient = np.einsum("kxi,kx->ki", feature_sens, w * residual.reshape(k, -1))
        diagonal = np.arange(m)
        hessian[:, diagonal, diagonal] += torque_weight
        gradient = gradient + torque_weight * deviation
        extra = damping * levenberg[:, None] * hessian[:, diagonal, diagonal].mean(1, keepdims=True)
        hessian[:, diagonal, diagonal] += extra + 1e-300
        return hessian, gradient

    def model_step(
        self,
        hessian0: np.ndarray,
        gradient0: np.ndarray,
        sens: np.ndarray,
        x: np.ndarray,
        limit: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        rho: float,
        rounds: int,
        max_qp_iterations: int,
        qp_tolerance: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        k = gradient0.shape[0]
        step = np.zeros_like(gradient0)
        qp_converged = np.zeros(k, bool)
        settled = np.zeros(k, bool) if rho > 0 else np.ones(k, bool)
        side = np.sign(x) * (np.abs(x) > limit)  # the bounds violated now: the first guess of A
        todo = np.arange(k)
        for _ in range(rounds if rho > 0 else 1):
            hessian, gradient = hessian0[todo], gradient0[todo]
            if rho > 0:  # penalty 1/2 rho |x_A + S_A d - b_A|^2 on the violated set A
                sens_on = sens[todo] * (side[todo] != 0)[..., None]
                hessian = hessian + rho * np.swapaxes(sens_on, 1, 2) @ sens_on
                gradient = gradient + rho * np.einsum("kxi,kx->ki", sens_on, x[todo] - side[todo] * limit)
            # warm start: the first round from the torques already on their limits (step = 0 there,
            # i.e. last Gauss-Newton step's active set), later rounds from the last round's step
            step[todo], qp_converged[todo] = solve_box_qp(
                hessian, gradient, lower[todo], upper[todo], max_qp_iterations, qp_tolerance, step[todo]
            )
            if rho == 0:
                break
            y = x[todo] + np.einsum("kxi,ki->kx", sens[todo], step[todo])
            new_side = np.sign(y) * (np.abs(y) > limit)
            same = np.all(new_side == side[todo], 1)
            settled[todo[same]] = True
            side[todo] = new_side
            todo = todo[~same]
            if todo.size == 0:
                break
        quadratic = np.einsum("ki,ki->k", gradient0, step) + 0.5 * np.einsum(
            "ki,ki->k", step, (hessian0 @ step[..., None])[..., 0]
        )
        y = x + np.einsum("kxi,ki->kx", sens, step)
        model_change = quadratic + _penalty(y, limit, rho) - _penalty(x, limit, rho)
        return step, -2.0 * model_change, settled & qp_converged  # the model is of J / 2

    def box_qp(
        self,
        hessian: np.ndarray,
        gradient: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        max_iterations: int,
        tolerance: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        return solve_box_qp(hessian, gradient, lower, upper, max_iterations, tolerance)


class NumbaInnerLoops:
    """Row by row in compiled code (``models.hmpc.kernels``, same signatures): no per-operation
    overhead, and in a batch no row waits for the slowest one's active-set loop. The kernels are
    compiled once per machine and loaded from numba's on-disk cache (~0.3-0.5 s per process)."""

    name = "numba"
    needs_warm_up = True

    def __init__(self) -> None:
        from models.hmpc import kernels  # numba's import takes ~0.5 s: only when chosen

        self.stage_cost = kernels.stage_cost
        self.sensitivities = kernels.sensitivities
        self.normal_equations = kernels.normal_equations
        self.model_step = kernels.model_step
        self.box_qp = kernels.box_qp


INNER_LOOPS: dict[str, type[NumpyInnerLoops] | type[NumbaInnerLoops]] = {
    "numpy": NumpyInnerLoops,
    "numba": NumbaInnerLoops,
}


def numba_installed() -> bool:
    return importlib.util.find_spec("numba") is not None


def make_inner_loops(choice: str) -> InnerLoops:
    """The inner loops named by ``HMPCConfig.kernels``: "numpy", "numba", or "auto" (numba when
    installed, else numpy)."""
    if choice == "auto":
        choice = "numba" if numba_installed() else "numpy"
    if choice not in INNER_LOOPS:
        raise ModelInputError(f"hmpc config kernels: unknown '{choice}' (known: auto, {', '.join(INNER_LOOPS)})")
    if choice == "numba" and not numba_installed():
        raise ModelInputError("hmpc config kernels: 'numba' needs the numba package (pip install numba)")
    return INNER_LOOPS[choice]()
