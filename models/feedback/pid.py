"""PID law (Sec. IV-B): the PD gains plus an integral of the position error.

    xi[k+1] = clip(xi[k] + dt e[k], -xi_max, xi_max)        (backward-rectangle integral, includes e[k])
    tau[k]  = sat(Kp e[k] + Kd e_dot[k] + Ki xi[k+1])

Kp = diag(25, 150, 65, 25, 2, 1), Kd = diag(1, 5, 2, 0.6, 0.1, 0.05), Ki = diag(0.3, 0.4, 0.3, 0.1, 0.03, 0.03).
The integral is clamped so that |Ki xi| never exceeds the torque limit: the paper gives no anti-windup,
and an unbounded integrator would keep growing while the torque saturates.
State: xi (B, N), the error integral in rad*s.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from models.feedback._common import const
from models.feedback.pd import PAPER_KD, PAPER_KP, PDLaw

PAPER_KI = np.array([0.3, 0.4, 0.3, 0.1, 0.03, 0.03])


class PIDLaw(PDLaw):
    """The PD law (its gains and torque) plus the clamped error integral."""

    name = "pid"

    def __init__(
        self,
        n_joints: int,
        period_s: float,
        torque_limit_nm: np.ndarray,
        kp: np.ndarray = PAPER_KP,
        kd: np.ndarray = PAPER_KD,
        ki: np.ndarray = PAPER_KI,
    ) -> None:
        super().__init__(n_joints, period_s, torque_limit_nm, kp, kd)
        self.ki = np.asarray(ki, float)
        # Anti-windup bound on the integral (rad*s); a large finite number where Ki = 0 keeps ONNX finite.
        self.integral_limit_rad_s = np.where(self.ki > 0, self.torque_limit_nm / np.maximum(self.ki, 1e-12), 1e6)
        # torch path: [q, qd, q_d, qd_d, integral] @ it = [integral + dt e, Kp e + Kd e_dot] (one MatMul)
        eye = np.eye(n_joints)
        rate = np.concatenate([-self.period_s * eye, 0 * eye, self.period_s * eye, 0 * eye, eye])
        self.pid_matrix = np.concatenate([rate, np.concatenate([self.pd_matrix, 0 * eye])], 1)

    @property
    def state_size(self) -> int:
        return self.n_joints

    @property
    def params(self) -> dict[str, Any]:
        return {
            **super().params,
            "ki": self.ki.tolist(),
            "integral_limit_rad_s": self.integral_limit_rad_s.tolist(),
            "integration": "backward rectangle",
        }

    def step(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any) -> tuple[Any, Any]:
        ki, limit = const(xp, self.ki), const(xp, self.integral_limit_rad_s)
        if xp is not np:  # traced for the ONNX graph: Concat, MatMul, Split, clamp, Gemm, saturation
            n = self.n_joints
            mapped = xp.concatenate([q, qd, q_d, qd_d, state], -1) @ const(xp, self.pid_matrix)
            stepped, pd = xp.split(mapped, [n, n], 1)
            integral = xp.minimum(xp.maximum(stepped, -limit), limit)
            return self.saturate(xp, xp.addmm(pd, integral, const(xp, np.diag(self.ki)))), integral
        e = q_d - q
        integral = xp.minimum(xp.maximum(state + self.period_s * e, -limit), limit)
        tau = self.pd_torque(xp, e, qd_d - qd) + ki * integral
        return self.saturate(xp, tau), integral
