"""check_plant on every TargetPlant implementation, and on plants that break each promise."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from sim_target.checks import PlantCheckError, check_plant
from sim_target.plant import PybulletPlant
from sim_target.plant_protocol import JointState
from sim_target.testing.fake_plant import FakePlant

Q0 = np.array([0.3, -0.5, 0.8, -0.4, 0.5, 0.2])


def test_the_pybullet_plant_passes() -> None:
    with PybulletPlant(period_s=1e-3, substeps=4, initial_position_rad=Q0) as plant:
        check_plant(plant)
        np.testing.assert_allclose(plant.state().position_rad, Q0, atol=1e-12)  # left reset


@pytest.mark.parametrize(("n", "period_s"), [(6, 1e-3), (2, 2e-3)])
def test_the_fake_plant_passes(n: int, period_s: float) -> None:
    check_plant(FakePlant(n, period_s), position_rad=np.linspace(-0.5, 0.5, n))


def test_the_fake_plant_and_its_state_type_import_no_pybullet() -> None:
    # why JointState and TargetPlant live in plant_protocol.py: the drive processes and benchmarks
    # that run the fake plant do not pay pybullet's import
    code = "import sys, sim_target.testing.fake_plant; sys.exit(1 if 'pybullet' in sys.modules else 0)"
    assert subprocess.run([sys.executable, "-c", code], check=False, timeout=60).returncode == 0


class _SlowClock(FakePlant):
    def step(self, torque_nm: np.ndarray, brake_engaged: np.ndarray) -> JointState:
        state = super().step(torque_nm, brake_engaged)
        return state._replace(time_s=2 * state.time_s)


class _LeakyBrake(FakePlant):
    def step(self, torque_nm: np.ndarray, brake_engaged: np.ndarray) -> JointState:
        return super().step(np.full(self.n_joints, 1.0), np.zeros(self.n_joints, dtype=bool))


class _Noisy(FakePlant):
    def step(self, torque_nm: np.ndarray, brake_engaged: np.ndarray) -> JointState:
        state = super().step(torque_nm, brake_engaged)
        return state._replace(position_rad=state.position_rad + np.random.default_rng().normal(size=self.n_joints))


class _WrongShape(FakePlant):
    def state(self) -> JointState:
        state = super().state()
        return state._replace(velocity_rad_s=state.velocity_rad_s[:-1])


@pytest.mark.parametrize(
    ("plant", "message"),
    [
        (_SlowClock(3, 1e-3), "time_s is 0.002, expected 1 x period_s"),
        (_LeakyBrake(3, 1e-3), "torque_nm .* is not the torque applied"),
        (_Noisy(3, 1e-3), "braked joint moved|not reproducible"),
        (_WrongShape(3, 1e-3), r"velocity_rad_s is not a float ndarray of shape \(3,\)"),
        (FakePlant(0, 1e-3), "n_joints is 0"),
        (FakePlant(3, 0.0), "period_s is 0.0"),
    ],
    ids=["clock", "brake", "noise", "shape", "no-joints", "no-period"],
)
def test_broken_plants_are_named(plant: FakePlant, message: str) -> None:
    with pytest.raises(PlantCheckError, match=message):
        check_plant(plant)
