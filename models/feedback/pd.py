"""PD law (Sec. IV-B): tau = Kp e + Kd e_dot, Kp = P = diag(25, 150, 65, 25, 2, 1)."""

from __future__ import annotations

from typing import Any

import numpy as np

from models.feedback._common import const
from models.feedback.base import FeedbackLaw

PAPER_KP = np.array([25.0, 150.0, 65.0, 25.0, 2.0, 1.0])
PAPER_KD = np.array([1.0, 5.0, 2.0, 0.6, 0.1, 0.05])


class PDLaw(FeedbackLaw):
    name = "pd"

    def __init__(
        self,
        n_joints: int,
        period_s: float,
        torque_limit_nm: np.ndarray,
        kp: np.ndarray = PAPER_KP,
        kd: np.ndarray = PAPER_KD,
    ) -> None:
        super().__init__(n_joints, period_s, torque_limit_nm)
        self.kp, self.kd = np.asarray(kp, float), np.asarray(kd, float)
        # the torch path's Kp e + Kd e_dot as one product of [q, qd, q_d, qd_d] (one ONNX MatMul for
        # five nodes: onnxruntime spends ~0.3 us per node, docs/lmpc.md t_L); numpy keeps the equation
        kp, kd = np.diag(np.broadcast_to(self.kp, (n_joints,))), np.diag(np.broadcast_to(self.kd, (n_joints,)))
        self.pd_matrix = np.concatenate([-kp, -kd, kp, kd])

    @property
    def params(self) -> dict[str, Any]:
        return {"kp": self.kp.tolist(), "kd": self.kd.tolist()}

    def pd_torque(self, xp: Any, e: Any, e_dot: Any) -> Any:
        """Kp e + Kd e_dot, unsaturated (PID adds its integral term to it)."""
        return const(xp, self.kp) * e + const(xp, self.kd) * e_dot

    def step(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any) -> tuple[Any, Any]:
        if xp is not np:
            tau = xp.concatenate([q, qd, q_d, qd_d], -1) @ const(xp, self.pd_matrix)
            return self.saturate(xp, tau), state
        return self.saturate(xp, self.pd_torque(xp, q_d - q, qd_d - qd)), state
