"""Parity (issue 5, item 5): the pybullet plant and the project's dynamics, driven by the same
torque law, agree on joint trajectories to 1e-3 rad over 2 s.

The torque is gravity compensation plus small sinusoids, evaluated on each simulator's own state at
the start of every 1 ms period and held over it (the HIL zero-order hold). The reference is the models
simulator's plant (models.sim.closed_loop: forward dynamics, own RNEFDA or pinocchio, with RK4; its
own integration error is ~1e-11 rad here). pybullet integrates with semi-implicit Euler, first order: the plant's default
32 substeps are what bring it under 1e-3 (benchmarks/bench_plant_parity.py has the whole table).
"""

from __future__ import annotations

import numpy as np
import pytest

from models.conditions import Mismatch
from models.dynamics import make_dynamics
from models.robots import load_robot
from models.sim.closed_loop import Plant as SimPlant
from models.sim.closed_loop import SimConfig
from sim_target.plant import PybulletPlant

PERIOD_S = 1e-3
DURATION_S = 2.0
Q0_RAD = np.array([0.3, -0.5, 0.8, -0.4, 0.5, 0.2])
FREQUENCY_HZ = np.array([0.8, 0.9, 1.0, 1.1, 1.2, 1.3])
# Sinusoid amplitude per joint: M_ii(q0) (2 pi f)^2 x 5 mrad. Coupling makes the actual moves
# 0.04-0.45 rad over the 2 s, all well inside the joint limits (pybullet enforces them, RK4 not).
EXCURSION_RAD = 0.005


def torque_law(dynamics, amplitude_nm: np.ndarray):  # type: ignore[no-untyped-def]
    def torque_nm(k: int, q: np.ndarray) -> np.ndarray:
        return dynamics.gravity(q) + amplitude_nm * np.sin(2 * np.pi * FREQUENCY_HZ * k * PERIOD_S)

    return torque_nm


def models_trajectory(robot, backend: str, torque_nm, n_periods: int) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The models simulator's plant (RK4, torque held over each period), nominal robot."""
    sim = SimPlant(robot, Mismatch(), SimConfig(dt_s=PERIOD_S, plant_backend=backend))
    q, qd = Q0_RAD.copy(), np.zeros_like(Q0_RAD)
    out = [q]
    for k in range(n_periods):
        q, qd = sim.integrate(q, qd, torque_nm(k, q), PERIOD_S)
        out.append(q)
    return np.array(out)


def plant_trajectory(torque_nm, n_periods: int, substeps: int | None = None) -> np.ndarray:  # type: ignore[no-untyped-def]
    kwargs = {} if substeps is None else {"substeps": substeps}
    with PybulletPlant(period_s=PERIOD_S, initial_position_rad=Q0_RAD, **kwargs) as plant:
        out = [plant.state().position_rad]
        free = np.zeros(plant.n_joints, dtype=bool)
        for k in range(n_periods):
            out.append(plant.step(torque_nm(k, plant.state().position_rad), free).position_rad)
    return np.array(out)


@pytest.mark.parametrize("backend", ["rne", "pinocchio"])
def test_plant_matches_the_project_dynamics_over_two_seconds(backend: str) -> None:
    robot = load_robot("ur5_paper")
    dynamics = make_dynamics(robot, backend=backend)
    amplitude_nm = np.diag(dynamics.mass_matrix(Q0_RAD)) * (2 * np.pi * FREQUENCY_HZ) ** 2 * EXCURSION_RAD
    law = torque_law(dynamics, amplitude_nm)
    n_periods = round(DURATION_S / PERIOD_S)
    reference = models_trajectory(robot, backend, law, n_periods)
    plant = plant_trajectory(law, n_periods)
    assert np.ptp(reference, axis=0).min() > 0.03  # every joint really moves
    error_rad = np.abs(plant - reference).max()
    assert error_rad < 1e-3, f"max joint error {error_rad:.2e} rad"
