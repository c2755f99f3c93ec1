"""The parity harness between the models simulator's plant and the pybullet plant: the same torque
law, evaluated on each simulator's own state at the start of every period and held over it (the
HIL zero-order hold), gives two joint trajectories to compare.

Used by tests/integration/test_plant_parity.py (agreement to 1e-3 rad over 2 s) and
benchmarks/bench_plant_parity.py (the error against the plant's substeps). The reference is the
models simulator's plant (forward dynamics, own RNEFDA or pinocchio, with RK4; its own integration
error is ~1e-11 rad here); pybullet integrates with semi-implicit Euler, first order.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from models.conditions import Mismatch
from models.sim.closed_loop import ModelPlant, SimConfig

PERIOD_S = 1e-3
DURATION_S = 2.0
Q0_RAD = np.array([0.3, -0.5, 0.8, -0.4, 0.5, 0.2])
FREQUENCY_HZ = np.array([0.8, 0.9, 1.0, 1.1, 1.2, 1.3])
# Sinusoid amplitude per joint: M_ii(q0) (2 pi f)^2 x 5 mrad. Coupling makes the actual moves
# 0.04-0.45 rad over the 2 s, all well inside the joint limits (pybullet enforces them, RK4 not).
EXCURSION_RAD = 0.005

TorqueLaw = Callable[[int, np.ndarray], np.ndarray]  # (period index k, q) -> torque_nm


def torque_law(dynamics: Any, amplitude_nm: np.ndarray) -> TorqueLaw:
    """Gravity compensation plus a sinusoid of ``amplitude_nm`` per joint at FREQUENCY_HZ."""

    def torque_nm(k: int, q: np.ndarray) -> np.ndarray:
        return dynamics.gravity(q) + amplitude_nm * np.sin(2 * np.pi * FREQUENCY_HZ * k * PERIOD_S)

    return torque_nm


def models_trajectory(robot: Any, backend: str, torque_nm: TorqueLaw, n_periods: int) -> np.ndarray:
    """The models simulator's plant (RK4, torque held over each period), nominal robot."""
    sim = ModelPlant(robot, Mismatch(), SimConfig(period_s=PERIOD_S, plant_backend=backend))
    q, qd = Q0_RAD.copy(), np.zeros_like(Q0_RAD)
    out = [q]
    for k in range(n_periods):
        q, qd = sim.integrate(q, qd, torque_nm(k, q), PERIOD_S)
        out.append(q)
    return np.array(out)


def plant_trajectory(torque_nm: TorqueLaw, n_periods: int, substeps: int | None = None) -> np.ndarray:
    """The pybullet plant of the simulated target, ``substeps`` physics steps per period."""
    from sim_target.plant import PybulletPlant  # pybullet: the sim extra

    kwargs = {} if substeps is None else {"substeps": substeps}
    with PybulletPlant(period_s=PERIOD_S, initial_position_rad=Q0_RAD, **kwargs) as plant:
        out = [plant.state().position_rad]
        free = np.zeros(plant.n_joints, dtype=bool)
        for k in range(n_periods):
            out.append(plant.step(torque_nm(k, plant.state().position_rad), free).position_rad)
    return np.array(out)
