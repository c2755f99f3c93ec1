"""Controllers the closed-loop simulator can run: the protocol, the feedback-only one, a stack.

A controller maps a batch of measured states and references to the torques to apply for the next
control period. Modes: ``fb`` (the law alone), ``hmpc`` (models.hmpc), ``lmpc`` (models.lmpc).
"""

from __future__ import annotations

import time
from typing import Any, Protocol

import numpy as np

from models.errors import ModelInputError
from models.feedback.base import FeedbackLaw
from models.robots import RobotModel

MODES = ("fb", "hmpc", "lmpc")


class Controller(Protocol):
    """What the simulator calls once per control period."""

    name: str
    #: wall time of each call (s); per-cycle cost for a single robot when the batch is 1
    cycle_times_s: list[float]

    def reset(self, q0: np.ndarray) -> None:
        """Start a run from positions q0 (B, N) at rest."""

    def __call__(
        self, t_s: float, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray
    ) -> np.ndarray:
        """Torques (B, N) to hold over the next period."""


class FeedbackController:
    """The feedback law alone (the paper's FB configuration)."""

    def __init__(self, law: FeedbackLaw) -> None:
        self.law = law
        self.name = f"{law.name}/fb"
        self.cycle_times_s: list[float] = []
        self.state = law.initial_state(np.zeros((1, law.n_joints)))
        self.last_tau_fb: np.ndarray | None = None

    def reset(self, q0: np.ndarray) -> None:
        self.state = self.law.initial_state(np.atleast_2d(q0))
        self.cycle_times_s = []

    def __call__(self, t_s, q, qd, q_d, qd_d, qdd_d):  # type: ignore[no-untyped-def]
        start = time.perf_counter()
        tau, self.state = self.law.step(np, self.state, q, qd, q_d, qd_d, qdd_d)
        self.last_tau_fb = tau
        self.cycle_times_s.append(time.perf_counter() - start)
        return tau


class ControllerStack:
    """Several controllers side by side over consecutive slices of one simulated batch.

    Lets one vectorized plant integration serve many (law, condition) runs at once.
    """

    def __init__(self, controllers: list[Any], sizes: list[int]) -> None:
        self.controllers, self.sizes = controllers, sizes
        self.name = "+".join(c.name for c in controllers)
        self.cycle_times_s: list[float] = []
        bounds = np.cumsum([0, *sizes])
        self.slices = [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
        self.last_tau_fb: np.ndarray | None = None

    def reset(self, q0: np.ndarray) -> None:
        for controller, part in zip(self.controllers, self.slices, strict=True):
            controller.reset(q0[part])

    def __call__(self, t_s, q, qd, q_d, qd_d, qdd_d):  # type: ignore[no-untyped-def]
        out = np.empty_like(q)
        fb = np.full_like(q, np.nan)
        for controller, part in zip(self.controllers, self.slices, strict=True):
            out[part] = controller(t_s, q[part], qd[part], q_d[part], qd_d[part], qdd_d[part])
            if getattr(controller, "last_tau_fb", None) is not None:
                fb[part] = controller.last_tau_fb
        self.last_tau_fb = fb
        return out


def make_controller(mode: str, law: FeedbackLaw, robot: RobotModel, **options: Any) -> Controller:
    """The controller of ``mode`` built on ``law`` for ``robot`` (the nominal model)."""
    if mode == "fb":
        return FeedbackController(law)
    if mode == "hmpc":
        from models.hmpc import make_hmpc_controller

        return make_hmpc_controller(law, robot, **options)
    if mode == "lmpc":
        from models.lmpc import make_lmpc_controller  # type: ignore[import-not-found]

        return make_lmpc_controller(law, robot, **options)
    raise ModelInputError(f"mode: unknown '{mode}' (known: {', '.join(MODES)})")
