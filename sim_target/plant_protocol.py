"""What every HIL target plant returns and promises, without pybullet.

``sim_target.plant.PybulletPlant`` and ``sim_target.testing.fake_plant.FakePlant`` both implement
``TargetPlant`` and return ``JointState``; the fake plant (and the drive processes and benchmarks
that use it) must not pay for importing pybullet, so the shared types live here, not in plant.py.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np


class JointState(NamedTuple):
    position_rad: np.ndarray  # (N,) measured (encoder noise included when enabled)
    velocity_rad_s: np.ndarray  # (N,) measured
    torque_nm: np.ndarray  # (N,) motor torque actually applied over the last period
    time_s: float  # simulated time


@runtime_checkable
class TargetPlant(Protocol):
    """The HIL target's physics, stepped by the emulated drives once per SYNC (``PybulletPlant``,
    ``sim_target.testing.fake_plant.FakePlant``); not the models' RK4 plant ``models.sim.ModelPlant``."""

    n_joints: int
    period_s: float

    def step(self, torque_nm: np.ndarray, brake_engaged: np.ndarray) -> JointState: ...

    def state(self) -> JointState: ...

    def reset(self, position_rad: np.ndarray | None = None) -> JointState: ...


__all__ = ["JointState", "TargetPlant"]
