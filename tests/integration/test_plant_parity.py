"""Parity (issue 5, item 5): the pybullet plant and the project's dynamics, driven by the same
torque law, agree on joint trajectories to 1e-3 rad over 2 s.

The torque is gravity compensation plus small sinusoids, evaluated on each simulator's own state at
the start of every 1 ms period and held over it (the HIL zero-order hold). The reference is the models
simulator's plant (models.sim.closed_loop: forward dynamics, own RNEFDA or pinocchio, with RK4; its
own integration error is ~1e-11 rad here). pybullet integrates with semi-implicit Euler, first
order: the plant's default 32 substeps are what bring it under 1e-3 (benchmarks/bench_plant_parity.py
has the whole table). The harness is models/sim/plant_parity.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from models.dynamics import make_dynamics
from models.robots import load_robot
from models.sim.plant_parity import (
    DURATION_S,
    EXCURSION_RAD,
    FREQUENCY_HZ,
    PERIOD_S,
    Q0_RAD,
    models_trajectory,
    plant_trajectory,
    torque_law,
)


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
