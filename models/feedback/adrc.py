"""ADRC law (Sec. IV-B): a linear extended state observer (ESO) per joint and a PD on the errors.

Per joint the plant is modelled as q_ddot = f + u with u = tau / b0: b0 is read as a torque per
acceleration (kg*m^2), close to this arm's joint inertias (docs/feedback_laws.md). The ESO, with
A = [[-b1, 1, 0], [-b2, 0, 1], [-b3, 0, 0]], inputs (q, u) and b1, b2, b3 = 3 wo, 3 wo^2, wo^3:

    z_dot = A z + [b1, b2, b3]^T q + [0, 1, 0]^T u

is discretized exactly for inputs held over one period (zero-order hold, matrix exponential):

    z[k] = Ad z[k-1] + Bq q[k] + Bu u_applied[k-1]          u_applied = tau_applied / b0
    tau[k] = sat(b0 * (kc_p e[k] + kc_d e_dot[k] + qdd_d[k] - z3[k]))     kc_p = wc^2, kc_d = 2 wc

The measured e and e_dot are used in the PD (the velocity is measured here, so no observer lag);
z3 is the total-disturbance estimate. The ESO is driven by the torque actually applied last period,
kept in the state at ``applied_torque_slice``: a caller that applies another torque (HMPC, a
clamp) writes it there. State (B, 4N): [z1 (rad), z2 (rad/s), z3 (rad/s^2), tau_applied (N*m)].

``b0_reading="gain"`` is the other reading (q_ddot = f + b0 tau, tau = u / b0); with b0[5] = 1e-4 it
asks 1e4 N*m per rad/s^2 and saturates at once (see docs/feedback_laws.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.linalg import expm

from models.errors import ModelInputError
from models.feedback._common import const
from models.feedback.base import FeedbackLaw

PAPER_B0 = np.array([0.015, 0.125, 0.070, 0.025, 0.008, 0.0001])
PAPER_OMEGA_O = 50.0
PAPER_OMEGA_C = 20.0


def eso_matrices(omega_o: float, period_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zero-order-hold discretization of the 3rd-order linear ESO: (Ad 3x3, Bq 3, Bu 3)."""
    b1, b2, b3 = 3 * omega_o, 3 * omega_o**2, omega_o**3
    a = np.array([[-b1, 1.0, 0.0], [-b2, 0.0, 1.0], [-b3, 0.0, 0.0]])
    b = np.array([[b1, 0.0], [b2, 1.0], [b3, 0.0]])
    block = np.zeros((5, 5))
    block[:3, :3], block[:3, 3:] = a, b
    discrete = expm(block * period_s)
    return discrete[:3, :3], discrete[:3, 3], discrete[:3, 4]


class ADRCLaw(FeedbackLaw):
    name = "adrc"

    def __init__(
        self,
        n_joints: int,
        period_s: float,
        torque_limit_nm: np.ndarray,
        b0: np.ndarray = PAPER_B0,
        omega_o: float = PAPER_OMEGA_O,
        omega_c: float = PAPER_OMEGA_C,
        b0_reading: str = "inertia",
    ) -> None:
        super().__init__(n_joints, period_s, torque_limit_nm)
        if b0_reading not in ("inertia", "gain"):
            raise ModelInputError(f"law 'adrc': b0_reading must be 'inertia' or 'gain', got '{b0_reading}'")
        self.b0 = np.asarray(b0, float)
        if np.any(self.b0 <= 0):
            raise ModelInputError(f"law 'adrc': b0 must be positive, got {self.b0.tolist()}")
        self.omega_o, self.omega_c, self.b0_reading = float(omega_o), float(omega_c), b0_reading
        self.eso_ad, self.eso_bq, self.eso_bu = eso_matrices(self.omega_o, self.period_s)
        # torque = torque_per_accel * u and u_applied = tau_applied / torque_per_accel, for either reading.
        self.torque_per_accel = self.b0 if b0_reading == "inertia" else 1.0 / self.b0
        n = n_joints
        self.applied_torque_slice = slice(3 * n, 4 * n)
        self.step_matrix = self._step_matrix()

    def _step_matrix(self) -> np.ndarray:
        """(9N, 4N): [q, qd, q_d, qd_d, qdd_d, state] @ it = [z[k] (3N), b0 u[k] before saturation (N)].

        The torch path's step as one product (an ONNX graph of 2 nodes instead of ~20: onnxruntime
        spends ~0.3 us per node, docs/lmpc.md t_L); the numpy path keeps the equations as written."""
        n, wc = self.n_joints, self.omega_c
        gain = np.broadcast_to(np.asarray(self.torque_per_accel, float), (n,))
        eye = np.eye(n)
        m = np.zeros((9 * n, 4 * n))
        for i in range(3):  # z_i[k] = sum_k Ad_ik z_k + Bq_i q + Bu_i tau_applied / gain
            cols = slice(i * n, (i + 1) * n)
            m[:n, cols] = self.eso_bq[i] * eye
            for k in range(3):
                m[(5 + k) * n : (6 + k) * n, cols] = self.eso_ad[i, k] * eye
            m[8 * n :, cols] = np.diag(self.eso_bu[i] / gain)
        u = slice(3 * n, 4 * n)  # gain (kc_p (q_d - q) + kc_d (qd_d - qd) + qdd_d - z3[k])
        m[:, u] = -m[:, 2 * n : 3 * n] * gain[None, :]
        for row, coefficient in ((0, -(wc**2)), (1, -2.0 * wc), (2, wc**2), (3, 2.0 * wc), (4, 1.0)):
            m[row * n : (row + 1) * n, u] += coefficient * np.diag(gain)
        return m

    @property
    def state_size(self) -> int:
        return 4 * self.n_joints

    @property
    def params(self) -> dict[str, Any]:
        wo = self.omega_o
        return {
            "b0": self.b0.tolist(),
            "b0_reading": self.b0_reading,
            "omega_o": wo,
            "omega_c": self.omega_c,
            "eso_gains": [3 * wo, 3 * wo**2, wo**3],
            "kc_p": self.omega_c**2,
            "kc_d": 2 * self.omega_c,
            "eso_discretization": "zero-order hold (exact)",
        }

    def initial_state(self, q0: np.ndarray) -> np.ndarray:
        """The observer starts at rest on the measured position: z1 = q0, z2 = z3 = 0, tau_applied = 0."""
        q0 = np.atleast_2d(np.asarray(q0, float))
        state = np.zeros((q0.shape[0], self.state_size))
        state[:, : self.n_joints] = q0
        return state

    def step(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any) -> tuple[Any, Any]:
        n = self.n_joints
        if xp is not np:  # traced for the ONNX graph: the same step as one product (_step_matrix)
            z_u = xp.concatenate([q, qd, q_d, qd_d, qdd_d, state], -1) @ const(xp, self.step_matrix)
            tau = self.saturate(xp, z_u[:, 3 * n :])
            return tau, xp.concatenate([z_u[:, : 3 * n], tau], -1)
        ad, bq, bu, gain = (const(xp, a) for a in (self.eso_ad, self.eso_bq, self.eso_bu, self.torque_per_accel))
        z = xp.reshape(state[:, : 3 * n], (-1, 3, n))
        u_applied = state[:, 3 * n :] / gain
        z = (
            xp.einsum("ij,bjn->bin", ad, z)
            + bq[None, :, None] * q[:, None, :]
            + bu[None, :, None] * u_applied[:, None, :]
        )
        u = self.omega_c**2 * (q_d - q) + 2.0 * self.omega_c * (qd_d - qd) + qdd_d - z[:, 2, :]
        tau = self.saturate(xp, gain * u)
        return tau, xp.concatenate([xp.reshape(z, (-1, 3 * n)), tau], -1)
