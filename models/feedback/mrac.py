"""MRAC law (Sec. IV-B): a Slotine-Li style adaptive law with a decentralized (per-joint) regressor.

    s = e_dot + Lambda e,   qd_r = qd_d + Lambda e,   qdd_r = qdd_d + Lambda e_dot
    Y_i = [qdd_r_i, qd_r_i, 1]          theta_i = [inertia (kg*m^2), viscous (N*m*s/rad), offset (N*m)]
    tau_i = sat(Y_i theta_i[k] + alpha_i s_i)
    theta_i[k+1] = clip(theta_i[k] + dt * gamma_i * Y_i^T s_i, theta_min_i, theta_max_i)

Names (the paper gives values, not equations): Lambda = diag(20, 20, 15, 10, 6, 2) 1/s is the
sliding-surface slope (Slotine and Li's Lambda); gamma = [5, 5, 4, 3, 1, 0.2] is the adaptation gain
Gamma_i = gamma_i I_3; alpha = [0.5, 0.5, 0.5, 0.5, 0.2, 0.2] N*m*s/rad is the damping K_D on s.
The paper's "V_dot = -s^T Lambda s" would make Lambda the damping K_D, but M^-1 diag(Lambda) dt reaches
16 at 1 kHz on this arm (a discrete velocity loop needs < 2), so Lambda cannot be a torque gain here.

The full Slotine-Li regressor of all inertial parameters needs the symbolic dynamics; the
decentralized one above adapts per joint an effective inertia, a viscous term and an offset that
absorbs gravity and coupling (an integral action on s). theta starts at [diag M^(q=0), 0, 0] and is
kept in a box (projection) so the law stays finite: inertia in [0.1, s] x diag M^(0) (s = 10 in the
"paper" gain set; 2 in "stabilized", since with 10 the adapted inertia outgrows the true one on
C4/C5 until the discrete velocity loop goes unstable),
|viscous| <= 1 N*m*s/rad, |offset| <= torque limit. State (B, 3N): [inertia, viscous, offset].
"""

from __future__ import annotations

from typing import Any

import numpy as np

from models.feedback._common import NominalModel, const
from models.feedback.base import FeedbackLaw
from models.robots import RobotModel

PAPER_ALPHA = np.array([0.5, 0.5, 0.5, 0.5, 0.2, 0.2])
PAPER_GAMMA = np.array([5.0, 5.0, 4.0, 3.0, 1.0, 0.2])
PAPER_LAMBDA = np.array([20.0, 20.0, 15.0, 10.0, 6.0, 2.0])
VISCOUS_BOUND_NM_S = 1.0


class MRACLaw(FeedbackLaw):
    name = "mrac"

    def __init__(
        self,
        robot: RobotModel,
        period_s: float,
        alpha: np.ndarray = PAPER_ALPHA,
        gamma: np.ndarray = PAPER_GAMMA,
        lam: np.ndarray = PAPER_LAMBDA,
        inertia_bound_scale: float = 10.0,
    ) -> None:
        super().__init__(robot.n_joints, period_s, robot.torque_limit_nm)
        self.alpha, self.gamma, self.lam = (np.asarray(g, float) for g in (alpha, gamma, lam))
        self.nominal_inertia_kg_m2 = NominalModel(robot).mass_matrix_diagonal(np.zeros(robot.n_joints))
        n = robot.n_joints
        self.theta_min = np.concatenate(
            [0.1 * self.nominal_inertia_kg_m2, np.full(n, -VISCOUS_BOUND_NM_S), -self.torque_limit_nm]
        )
        self.theta_max = np.concatenate(
            [inertia_bound_scale * self.nominal_inertia_kg_m2, np.full(n, VISCOUS_BOUND_NM_S), self.torque_limit_nm]
        )
        self.step_map = self._step_map()

    def _step_map(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A (5N, 7N), b (7N), sum (3N, N)) for the torch path: [q, qd, q_d, qd_d, qdd_d] @ A + b =
        [Y (qdd_r, qd_r, 1), dt gamma s thrice, alpha s], then tau = (theta * Y) @ sum + alpha s and
        theta' = theta + Y * (dt gamma s): ~11 ONNX nodes instead of ~26 (onnxruntime spends ~0.3 us per
        node, docs/lmpc.md t_L); the numpy path keeps the equations as written."""
        n, lam = self.n_joints, self.lam
        eye = np.eye(n)
        # e = q_d - q and e_dot = qd_d - qd as rows of the five signals
        e = np.concatenate([-eye, 0 * eye, eye, 0 * eye, 0 * eye])
        e_dot = np.concatenate([0 * eye, -eye, 0 * eye, eye, 0 * eye])
        qd_d, qdd_d = (np.concatenate([eye if k == j else 0 * eye for k in range(5)]) for j in (3, 4))
        s = e_dot + e * lam[None, :]
        columns = [qdd_d + e_dot * lam[None, :], qd_d + e * lam[None, :], np.zeros((5 * n, n))]
        columns += [s * (self.period_s * self.gamma)[None, :]] * 3 + [s * self.alpha[None, :]]
        bias = np.zeros(7 * n)
        bias[2 * n : 3 * n] = 1.0
        return np.concatenate(columns, 1), bias, np.concatenate([eye, eye, eye])

    @property
    def state_size(self) -> int:
        return 3 * self.n_joints

    @property
    def params(self) -> dict[str, Any]:
        return {
            "alpha_kd": self.alpha.tolist(),
            "gamma": self.gamma.tolist(),
            "lambda": self.lam.tolist(),
            "regressor": "per joint [qdd_r, qd_r, 1]",
            "theta0": self._theta0().tolist(),
            "theta_min": self.theta_min.tolist(),
            "theta_max": self.theta_max.tolist(),
        }

    def _theta0(self) -> np.ndarray:
        return np.concatenate([self.nominal_inertia_kg_m2, np.zeros(2 * self.n_joints)])

    def initial_state(self, q0: np.ndarray) -> np.ndarray:
        return np.tile(self._theta0(), (np.atleast_2d(q0).shape[0], 1))

    def step(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any) -> tuple[Any, Any]:
        n = self.n_joints
        if xp is not np:  # traced for the ONNX graph: the same step as two products (_step_map)
            a, b, total = (const(xp, v) for v in self.step_map)
            lo, hi = const(xp, self.theta_min), const(xp, self.theta_max)
            mapped = xp.addmm(b, xp.concatenate([q, qd, q_d, qd_d, qdd_d], -1), a)
            y, rate, damping = xp.split(mapped, [3 * n, 3 * n, n], 1)
            tau = xp.addmm(damping, state * y, total)
            theta = xp.minimum(xp.maximum(state + y * rate, lo), hi)
            return self.saturate(xp, tau), theta
        alpha, gamma, lam, lo, hi = (
            const(xp, a) for a in (self.alpha, self.gamma, self.lam, self.theta_min, self.theta_max)
        )
        e, e_dot = q_d - q, qd_d - qd
        s = e_dot + lam * e
        qd_r, qdd_r = qd_d + lam * e, qdd_d + lam * e_dot
        inertia, viscous, offset = state[:, :n], state[:, n : 2 * n], state[:, 2 * n :]
        tau = inertia * qdd_r + viscous * qd_r + offset + alpha * s
        gradient = xp.concatenate([qdd_r * s, qd_r * s, s], -1) * xp.concatenate([gamma, gamma, gamma], -1)
        theta = xp.minimum(xp.maximum(state + self.period_s * gradient, lo), hi)
        return self.saturate(xp, tau), theta
