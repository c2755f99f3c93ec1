"""The HMPC as a closed-loop controller (the simulator's ``Controller`` protocol).

    controller = make_hmpc_controller(law, robot, backend="pinocchio", max_iterations=4)
    controller.reset(q0)                       # (B, N)
    tau = controller(t_s, q, qd, q_d, qd_d, qdd_d)

Per call it steps the law (its state kept here), solves the MPC for the batch, records the torque
actually applied into the law's state (ADRC's observer needs it), and keeps the optimal sequence
to warm-start the next call. ``cycle_times_s`` holds the wall time of every call; ``fallbacks``
counts, per reason, the rows that got the feedback torque instead of the MPC's.
"""

from __future__ import annotations

import time
from collections import Counter
from typing import Any

import numpy as np

from models.feedback.base import FeedbackLaw
from models.hmpc.config import HMPCConfig
from models.hmpc.result import STATUS_NAMES, HMPCResult
from models.hmpc.solver import HMPCSolver
from models.robots import RobotModel


class HMPCController:
    """HMPC on top of one feedback law, for a batch of B independent arms."""

    def __init__(self, law: FeedbackLaw, robot: RobotModel, config: HMPCConfig | None = None) -> None:
        self.solver = HMPCSolver(law, robot, config)
        self.law, self.config = law, self.solver.config
        self.name = f"{law.name}/hmpc"
        self.cycle_times_s: list[float] = []
        self.fallbacks: Counter[str] = Counter()
        self.iterations: list[int] = []  # Gauss-Newton iterations, summed over the batch, per call
        self.last_tau_fb: np.ndarray | None = None
        self.last_result: HMPCResult | None = None
        self.state: np.ndarray | None = None  # the law's state (B, S), as FeedbackController.state
        self._sequence: np.ndarray | None = None
        self._applied: np.ndarray | None = None

    @property
    def fallback_count(self) -> int:
        """Rows, over all calls since reset, that got the fallback torque."""
        return sum(self.fallbacks.values())

    def reset(self, q0: np.ndarray) -> None:
        q0 = np.atleast_2d(np.asarray(q0, float))
        self.state = self.law.initial_state(q0)
        self._sequence, self._applied = None, None
        self.cycle_times_s, self.iterations = [], []
        self.fallbacks = Counter()

    def __call__(
        self, t_s: float, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray
    ) -> np.ndarray:
        start = time.perf_counter()
        if self.state is None:
            self.reset(q)
        result = self.solver.solve(
            q, qd, q_d, qd_d, qdd_d, self.state, self._sequence, self._applied, previous_torque_nm=self._applied
        )
        self.state = result.law_state
        self._sequence = result.sequence_nm
        self._applied = result.tau_nm
        self.cycle_times_s.append(time.perf_counter() - start)
        self.last_tau_fb, self.last_result = result.tau_fb_nm, result
        self.iterations.append(int(result.iterations.sum()))
        for code in result.status[result.fell_back]:
            self.fallbacks[STATUS_NAMES[int(code)]] += 1
        return result.tau_nm


def make_hmpc_controller(law: FeedbackLaw, robot: RobotModel, **options: Any) -> HMPCController:
    """The HMPC controller on ``law`` for the nominal ``robot``; options are HMPCConfig fields
    (or ``config=HMPCConfig(...)``)."""
    config = options.pop("config", None)
    if config is None:
        config = HMPCConfig.from_options(**options)
    elif options:
        config = HMPCConfig.from_options(**{**config.__dict__, **options})
    return HMPCController(law, robot, config)
