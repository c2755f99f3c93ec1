"""Fixtures of the HMPC tests: the paper's arm, states near a moving reference, random box QPs."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from models.robots import RobotModel, load_robot

States = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
BoxQPs = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
MakeStates = Callable[..., States]
MakeBoxQPs = Callable[..., BoxQPs]
Objective = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


@pytest.fixture(scope="session")
def robot() -> RobotModel:
    return load_robot("ur5_paper")


def near_reference_states(batch: int, seed: int = 0, error_rad: float = 0.01) -> States:
    """(q, qd, q_d, qd_d, qdd_d) (batch, 6): arm states near a moving reference, as in closed loop
    (position errors of ``error_rad``, velocity errors 5x that)."""
    rng = np.random.default_rng(seed)
    q_d = rng.uniform(-1.0, 1.0, (batch, 6))
    qd_d = rng.uniform(-0.3, 0.3, (batch, 6))
    qdd_d = rng.uniform(-0.2, 0.2, (batch, 6))
    q = q_d + rng.normal(0.0, error_rad, (batch, 6))
    qd = qd_d + rng.normal(0.0, 5 * error_rad, (batch, 6))
    return q, qd, q_d, qd_d, qdd_d


def random_box_qps(seed: int, rows: int = 12, size: int = 30, unit_lower: bool = False) -> BoxQPs:
    """(H (K, n, n), g, lower, upper (K, n)): ill-conditioned positive definite H (column scales
    1e-3..10, as the torque sequence's), bounds around 0 that cut the unconstrained minimizer."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(rows, size, size)) * np.logspace(-3, 1, size)
    hessian = a @ np.swapaxes(a, 1, 2) + 1e-6 * np.eye(size)
    gradient = rng.normal(size=(rows, size)) * 10
    lower = -np.ones((rows, size)) if unit_lower else -rng.uniform(0.1, 2.0, (rows, size))
    upper = rng.uniform(0.1, 2.0, (rows, size))
    return hessian, gradient, lower, upper


def qp_objective(hessian: np.ndarray, gradient: np.ndarray, x: np.ndarray) -> np.ndarray:
    """g'x + 1/2 x'Hx per row (K,)."""
    value: np.ndarray = np.einsum("ki,ki->k", gradient + 0.5 * np.einsum("kij,kj->ki", hessian, x), x)
    return value


@pytest.fixture(scope="session")
def make_states() -> MakeStates:
    return near_reference_states


@pytest.fixture(scope="session")
def make_box_qps() -> MakeBoxQPs:
    return random_box_qps


@pytest.fixture(scope="session")
def objective() -> Objective:
    return qp_objective
