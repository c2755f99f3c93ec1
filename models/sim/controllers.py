"""Controllers the closed-loop simulator can run: the protocol, the feedback-only one, a stack, and
the registry of modes.

A controller maps a batch of measured states and references to the torques to apply for the next
control period. A mode is a name -> factory ``(law, robot, **options) -> Controller`` entry, filled
in by the package that implements it, as Gymnasium's ``register``/``make``: this module registers
``fb`` (the law alone); ``models.modes`` registers ``hmpc`` and ``lmpc`` by entry point
("module:attribute", imported when first made), so the simulator never imports the MPC packages.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from models.errors import ModelInputError
from models.feedback.base import FeedbackLaw
from models.robots import RobotModel


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

    def __call__(
        self, t_s: float, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray
    ) -> np.ndarray:
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

    def __call__(
        self, t_s: float, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray
    ) -> np.ndarray:
        out = np.empty_like(q)
        fb = np.full_like(q, np.nan)
        for controller, part in zip(self.controllers, self.slices, strict=True):
            out[part] = controller(t_s, q[part], qd[part], q_d[part], qd_d[part], qdd_d[part])
            if getattr(controller, "last_tau_fb", None) is not None:
                fb[part] = controller.last_tau_fb
        self.last_tau_fb = fb
        return out

    def commit(self, applied_torque_nm: np.ndarray) -> None:
        """The commanded torques (B, N) after the simulator's saturation, to each part that takes them."""
        for controller, part in zip(self.controllers, self.slices, strict=True):
            commit = getattr(controller, "commit", None)
            if commit is not None:
                commit(applied_torque_nm[part])


#: (law, robot, **options) -> Controller
ControllerFactory = Callable[..., Controller]
_MODES: dict[str, ControllerFactory | str] = {}


def register_mode(name: str, factory: ControllerFactory | str) -> None:
    """Register mode ``name``: a factory, or its entry point "module:attribute" (imported when first made)."""
    if isinstance(factory, str) and factory.count(":") != 1:
        raise ValueError(f"mode '{name}': entry point must be 'module:attribute', got {factory!r}")
    known = _MODES.get(name)
    if known is not None and known != factory:
        raise ValueError(f"mode '{name}' is already registered ({known!r})")
    _MODES[name] = factory


def mode_names() -> tuple[str, ...]:
    """The registered modes, in registration order."""
    return tuple(_MODES)


def make_controller(mode: str, law: FeedbackLaw, robot: RobotModel, **options: Any) -> Controller:
    """The controller of ``mode`` built on ``law`` for ``robot`` (the nominal model)."""
    factory = _MODES.get(mode)
    if factory is None:
        raise ModelInputError(f"mode: unknown '{mode}' (known: {', '.join(_MODES)})")
    if isinstance(factory, str):
        module, attribute = factory.split(":")
        factory = _MODES[mode] = getattr(importlib.import_module(module), attribute)
    return factory(law, robot, **options)


def _feedback_only(law: FeedbackLaw, robot: RobotModel) -> FeedbackController:
    return FeedbackController(law)  # the law already holds what it needs of the robot


register_mode("fb", _feedback_only)
