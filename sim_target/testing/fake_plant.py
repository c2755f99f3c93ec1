"""A tiny plant for the drive-bus tests and benchmarks: independent joints, one inertia.

Implements sim_target.plant_protocol.TargetPlant without pybullet: each joint is a double
integrator (torque / inertia), a braked joint is held still. Deterministic, microseconds per step.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from sim_target.plant_protocol import JointState

if TYPE_CHECKING:
    from sim_target.drives import EmulatedDrives


class FakePlant:
    def __init__(self, n_joints: int, period_s: float, inertia_kg_m2: float = 0.5) -> None:
        self.n_joints = n_joints
        self.period_s = period_s
        self.inertia_kg_m2 = inertia_kg_m2
        self.steps = 0
        self.reset()

    def reset(self, position_rad: np.ndarray | None = None) -> JointState:
        self._q = np.zeros(self.n_joints) if position_rad is None else np.array(position_rad, dtype=float)
        self._v = np.zeros(self.n_joints)
        self._tau = np.zeros(self.n_joints)
        self._t = 0.0
        return self.state()

    def state(self) -> JointState:
        return JointState(self._q.copy(), self._v.copy(), self._tau.copy(), self._t)

    def step(self, torque_nm: np.ndarray, brake_engaged: np.ndarray) -> JointState:
        torque = np.where(brake_engaged, 0.0, np.asarray(torque_nm, dtype=float))
        self._v = np.where(brake_engaged, 0.0, self._v + torque / self.inertia_kg_m2 * self.period_s)
        self._q = self._q + self._v * self.period_s  # semi-implicit Euler
        self._tau = torque
        self._t += self.period_s
        self.steps += 1
        return self.state()


def lockstep(drives: EmulatedDrives, plant: FakePlant) -> None:
    """Wire ``plant`` to emulated drives the way the target server does in lock-step mode."""

    def on_sync() -> None:
        enabled = drives.operation_enabled()
        state = plant.step(np.where(enabled, drives.commanded_torque_nm(), 0.0), ~enabled)
        drives.publish_feedback(state)

    drives.set_sync_handler(on_sync)
