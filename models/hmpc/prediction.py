"""The MPC's prediction model: nominal forward dynamics, its derivatives, and the discrete step.

Two interchangeable backends on the same robot description:

- ``pinocchio``: C++ ABA (``abaInParallel`` over a batch in one call) and the analytic ABA
  derivatives (``computeABADerivatives``). The fast one.
- ``rne``: the project's own RNEFDA (Alg. 1), vectorized over the batch in numpy. Its derivatives
  are exact too: d(qdd)/dtau = M^-1, and d(qdd)/d(q, qd) = -M^-1 d(ID)/d(q, qd) at qdd, with the
  RNEIDA partials taken by complex-step differentiation (Im f(x + i h) / h, h = 1e-30), which has no
  cancellation error. Both backends therefore give the same derivatives to round-off, so the
  optimizer takes the same steps (the HMPC outputs agree to 1e-8; a test checks it).

Discretization (one control period dt, torque held): semi-implicit Euler,
    qd+ = qd + dt * qdd(q, qd, tau),    q+ = q + dt * qd+.
It is symplectic-like (no energy drift), needs one dynamics call per step, and its Jacobians are
cheap; over the 5-step preview its difference from the simulator's RK4 plant is O(dt^2) per step.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from models.dynamics.rne import ChainArrays, mass_matrix_and_bias, rneida
from models.errors import ModelInputError
from models.robots import RobotModel

COMPLEX_STEP = 1e-30


class Predictor(Protocol):
    """Batched nominal forward dynamics and its first derivatives."""

    n_joints: int

    def acceleration(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """qdd (K, N) for states and torques (K, N)."""

    def acceleration_derivatives(
        self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(qdd (K, N), dqdd/dq, dqdd/dqd, dqdd/dtau (K, N, N) each)."""


class PinocchioPredictor:
    """pinocchio's ABA and analytic ABA derivatives (C++)."""

    def __init__(self, robot: RobotModel) -> None:
        try:
            import pinocchio as pin
        except ImportError as exc:  # pragma: no cover - depends on the install
            raise ModelInputError(
                "hmpc backend 'pinocchio': the pin package is not installed (pip install pin)"
            ) from exc
        from models.dynamics.backends import build_pinocchio_model

        self._pin = pin
        self.n_joints = robot.n_joints
        self.model = build_pinocchio_model(robot)
        self.data = self.model.createData()
        # One model/data in the pool, one thread: the 1 kHz loop must not wait on thread start-up,
        # and batch labeling gets its parallelism from processes (models.hmpc.batch).
        self._pool = pin.ModelPool(self.model, 1)

    def __getstate__(self) -> dict:  # pinocchio objects are rebuilt in worker processes
        raise TypeError("PinocchioPredictor is built per process; pickle the HMPCSolver's spec instead")

    def acceleration(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> np.ndarray:
        # (K, N) C-contiguous transposes to the (N, K) column-major layout pinocchio wants: no copy.
        if q.shape[0] == 1:  # one state (the 1 kHz loop): the plain call has less set-up
            return self._pin.aba(self.model, self.data, q[0], qd[0], tau[0])[None].copy()
        q, qd, tau = (np.ascontiguousarray(a, dtype=np.float64) for a in (q, qd, tau))
        return self._pin.abaInParallel(1, self._pool, q.T, qd.T, tau.T).T

    def acceleration_derivatives(self, q, qd, tau):  # type: ignore[no-untyped-def]
        pin, model, data = self._pin, self.model, self.data
        k, n = q.shape
        qdd = np.empty((k, n))
        d_q, d_qd, d_tau = np.empty((k, n, n)), np.empty((k, n, n)), np.empty((k, n, n))
        for row in range(k):
            # The returned arrays alias pinocchio's data: copy them out before the next call.
            d_q[row], d_qd[row], d_tau[row] = pin.computeABADerivatives(model, data, q[row], qd[row], tau[row])
            qdd[row] = data.ddq
        return qdd, d_q, d_qd, d_tau


class RnePredictor:
    """The project's own RNEFDA (the paper's Alg. 1), batched in numpy; exact derivatives."""

    def __init__(self, robot: RobotModel) -> None:
        self.n_joints = robot.n_joints
        self.chain = ChainArrays.from_robot(robot)

    def acceleration(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> np.ndarray:
        mass_matrix, bias = mass_matrix_and_bias(np, self.chain, q, qd)
        return np.linalg.solve(mass_matrix, (tau - bias)[..., None])[..., 0]

    def acceleration_derivatives(self, q, qd, tau):  # type: ignore[no-untyped-def]
        k, n = q.shape
        mass_matrix, bias = mass_matrix_and_bias(np, self.chain, q, qd)
        m_inv = np.linalg.inv(mass_matrix)
        qdd = np.einsum("kij,kj->ki", m_inv, tau - bias)
        # RNEIDA at (q, qd, qdd) perturbed along each q_i and each qd_i by i*h: 2N complex rows per state.
        eye = np.eye(n) * (1j * COMPLEX_STEP)
        q_rows = np.concatenate([q[:, None, :] + eye, np.broadcast_to(q[:, None, :], (k, n, n))], 1)
        qd_rows = np.concatenate([np.broadcast_to(qd[:, None, :], (k, n, n)), qd[:, None, :] + eye], 1)
        qdd_rows = np.broadcast_to(qdd[:, None, :], (k, 2 * n, n)).astype(complex)
        tau_rows = rneida(
            np, self.chain, q_rows.reshape(-1, n), qd_rows.reshape(-1, n), qdd_rows.reshape(-1, n), self.chain.gravity
        )
        partials = tau_rows.imag.reshape(k, 2 * n, n) / COMPLEX_STEP  # row i: d(ID)/d(x_i)
        d_id_dq = np.swapaxes(partials[:, :n], 1, 2)
        d_id_dqd = np.swapaxes(partials[:, n:], 1, 2)
        return qdd, -m_inv @ d_id_dq, -m_inv @ d_id_dqd, m_inv


PREDICTORS = {"pinocchio": PinocchioPredictor, "rne": RnePredictor}


def make_predictor(robot: RobotModel, backend: str) -> Predictor:
    """The nominal prediction model of ``robot`` from the named backend."""
    if backend not in PREDICTORS:
        raise ModelInputError(f"hmpc backend: unknown '{backend}' (known: {', '.join(PREDICTORS)})")
    return PREDICTORS[backend](robot)
