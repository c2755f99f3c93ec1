"""SMC law (Sec. IV-B): sliding surface, boundary-layer switching, and computed-torque equivalent control.

    s = e_dot + lambda * e
    tau = sat_tau( M^(q) (qdd_d + lambda * e_dot) + h^(q, qd) + K_sw(q) sat(s / eps) )

M^(q)(qdd_d + lambda e_dot) + h^(q, qd) is the equivalent control, evaluated as ONE RNEIDA call of the
nominal model: ID^(q, qd, qdd_d + lambda e_dot). With an exact model it gives M s_dot = -K_sw sat(s/eps).

The paper's switching gains k = [0.05, 0.10, 0.10, 0.15, 0.20, 0.005] are read literally as torques
(``switching_units="torque"``, default: K_sw = diag(k) N*m), as the paper's "k ensures s_i s_i_dot < 0 ...
counter coupling effects" suggests. In the boundary layer this is a gain M^-1 k / eps whose largest
eigenvalue times dt = 1 ms is about 9 > 2 on this arm, so at 1 kHz the layer acts as a relay of
amplitude k (bounded chattering, at most 0.2 N*m). The other reading (``"acceleration"``:
K_sw sat = M^(q) (k * sat), one more term in the same RNEIDA call, s_dot = -k sat(s/eps)) is smooth
but recovers from the paper's impulse at only k rad/s^2 (0.005 on joint 6) and drifts by hundreds of
degrees on the paper's conditions (docs/feedback_laws.md).
Values: lambda = [5, 3, 3, 5, 2, 0.05] 1/s, eps = 0.02 (rad/s). No state.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from models.errors import ModelInputError
from models.feedback._common import NominalModel, const, sat
from models.feedback.base import FeedbackLaw, SharedId
from models.robots import RobotModel

PAPER_LAMBDA = np.array([5.0, 3.0, 3.0, 5.0, 2.0, 0.05])
PAPER_K = np.array([0.05, 0.10, 0.10, 0.15, 0.20, 0.005])
PAPER_EPSILON = 0.02


class SMCLaw(FeedbackLaw):
    name = "smc"

    def __init__(
        self,
        robot: RobotModel,
        period_s: float,
        lam: np.ndarray = PAPER_LAMBDA,
        k: np.ndarray = PAPER_K,
        epsilon: float = PAPER_EPSILON,
        switching_units: str = "torque",
    ) -> None:
        super().__init__(robot.n_joints, period_s, robot.torque_limit_nm)
        if switching_units not in ("acceleration", "torque"):
            raise ModelInputError(
                f"law 'smc': switching_units must be 'acceleration' or 'torque', got '{switching_units}'"
            )
        if not epsilon > 0:
            raise ModelInputError(f"law 'smc': epsilon must be positive, got {epsilon}")
        self.lam, self.k = np.asarray(lam, float), np.asarray(k, float)
        self.epsilon, self.switching_units = float(epsilon), switching_units
        self.nominal = NominalModel(robot)

    @property
    def params(self) -> dict[str, Any]:
        return {
            "lambda": self.lam.tolist(),
            "k": self.k.tolist(),
            "epsilon": self.epsilon,
            "switching_units": self.switching_units,
            "equivalent_control": "computed torque ID^(q, qd, qdd_d + lambda e_dot), one RNEIDA call",
        }

    def step(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any) -> tuple[Any, Any]:
        tau, nxt, _ = self.step_sharing_id(xp, state, q, qd, q_d, qd_d, qdd_d, None)
        return tau, nxt

    def step_sharing_id(
        self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any, shared: SharedId | None
    ) -> tuple[Any, Any, Any]:
        lam, k = const(xp, self.lam), const(xp, self.k)
        e, e_dot = q_d - q, qd_d - qd
        switching = k * sat(xp, (e_dot + lam * e) / self.epsilon)
        qdd_ref = qdd_d + lam * e_dot
        qdd = qdd_ref + switching if self.switching_units == "acceleration" else qdd_ref
        if xp is np:
            tau, shared_tau = self.nominal.inverse_dynamics(xp, q, qd, qdd), None
        else:
            tau, shared_tau = self.nominal.inverse_dynamics_sharing(q, qd, qdd, shared)
        if self.switching_units != "acceleration":
            tau = tau + switching
        return self.saturate(xp, tau), state, shared_tau
