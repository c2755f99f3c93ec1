"""The MPC's prediction model: nominal forward dynamics, its derivatives, and the discrete step.

The dynamics are built by models.dynamics (the one place that does): backend ``pinocchio`` (C++ ABA,
``abaInParallel`` over a batch, analytic ABA derivatives; the fast one) or ``rne`` (the project's own
RNEFDA, the paper's Alg. 1, batched in numpy, with exact complex-step RNEIDA partials). Both give the
same derivatives to round-off, so the optimizer takes the same steps (the HMPC outputs agree to 1e-8;
a test checks it).

Discretization (one prediction step dt, torque held): semi-implicit Euler,
    qd+ = qd + dt * qdd(q, qd, tau),    q+ = q + dt * qd+.
It is symplectic-like (no energy drift), needs one dynamics call per step, and its Jacobians are
cheap; over the 5-step preview its difference from the simulator's RK4 plant is O(dt^2) per step.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from models.dynamics import Dynamics, make_dynamics
from models.errors import ModelInputError
from models.robots import RobotModel

BACKENDS = ("pinocchio", "rne")


class Predictor(Protocol):
    """Batched nominal forward dynamics and its first derivatives."""

    n_joints: int

    def acceleration(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """qdd (K, N) for states and torques (K, N)."""

    def acceleration_derivatives(
        self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(qdd (K, N), dqdd/dq, dqdd/dqd, dqdd/dtau (K, N, N) each)."""


class DynamicsPredictor:
    """A models.dynamics backend seen as the MPC's predictor (batched (K, N) calls only)."""

    # the backend's bound methods themselves: no extra Python frame on the solver's hot path
    acceleration: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
    acceleration_derivatives: Callable[
        [np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    ]

    def __init__(self, dynamics: Dynamics) -> None:
        self.dynamics = dynamics
        self.n_joints = dynamics.n_joints
        self.acceleration = dynamics.forward_dynamics
        self.acceleration_derivatives = dynamics.forward_dynamics_derivatives

    def __getstate__(self) -> dict:  # pinocchio objects are rebuilt in worker processes
        raise TypeError("the HMPC predictor is built per process; pickle the HMPCSolver's spec instead")


def make_predictor(robot: RobotModel, backend: str) -> Predictor:
    """The nominal prediction model of ``robot`` from the named models.dynamics backend."""
    if backend not in BACKENDS:
        raise ModelInputError(f"hmpc backend: unknown '{backend}' (known: {', '.join(BACKENDS)})")
    return DynamicsPredictor(make_dynamics(robot, backend))
