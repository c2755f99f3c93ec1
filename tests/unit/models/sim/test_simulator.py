from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from models.conditions import Condition, Disturbance, Mismatch, load_conditions
from models.dynamics import make_dynamics
from models.errors import ModelInputError
from models.feedback.pd import PDLaw
from models.robots import load_robot
from models.sim import ControllerStack, FeedbackController, SimConfig, simulate

ROBOT = load_robot("ur5_paper")
SHORT = [
    replace(c, duration_s=0.5, disturbance=replace(c.disturbance, time_s=0.2)) for c in load_conditions(robot=ROBOT)[:2]
]


class GravityCompensation:
    """Holds the arm still: the exact gravity torque of the nominal model."""

    name = "gravity"

    def __init__(self) -> None:
        self.dyn = make_dynamics(ROBOT)
        self.cycle_times_s: list[float] = []

    def reset(self, q0: np.ndarray) -> None:
        pass

    def __call__(self, t_s, q, qd, q_d, qd_d, qdd_d):
        return self.dyn.gravity(q)


def test_gravity_compensation_holds_still_and_pulse_gives_the_impulse() -> None:
    still = Condition(
        name="still",
        amplitude_rad=(0.3, 0.4, -0.5, 0.2, 0.1, 0.0),
        frequency_hz=(0.1,) * 6,
        shape="constant",
        initial_state="reference",
        duration_s=0.3,
        disturbance=None,
    )
    traj = simulate(ROBOT, GravityCompensation(), [still])
    assert np.abs(traj.q[0] - traj.q[0, 0]).max() < 1e-9
    # A pulse J = tau * d on a resting arm changes velocity by M^-1 J (to first order in d).
    pulse = Disturbance(time_s=0.1005, torque_nm=(1, 1, 5, 5, 10, 10), duration_s=2e-5)
    kicked = simulate(ROBOT, GravityCompensation(), [replace(still, disturbance=pulse)])
    expected = np.linalg.solve(make_dynamics(ROBOT).mass_matrix(traj.q[0, 0]), pulse.impulse_nm_s)
    assert kicked.qd[0, 101] == pytest.approx(expected, rel=2e-2, abs=1e-3)


def test_batch_equals_single_runs_and_stack_dispatches() -> None:
    law = PDLaw(6, 1e-3, ROBOT.torque_limit_nm)
    both = simulate(ROBOT, FeedbackController(law), SHORT)
    one = simulate(ROBOT, FeedbackController(law), SHORT[1:])
    assert both.q[1] == pytest.approx(one.q[0], abs=1e-12)
    stack = ControllerStack([FeedbackController(law), FeedbackController(law)], [2, 2])
    stacked = simulate(ROBOT, stack, SHORT + SHORT)
    assert stacked.q[2:] == pytest.approx(both.q, abs=1e-12)
    assert stacked.tau_fb is not None and np.isfinite(stacked.tau_fb).all()


def test_rk4_substeps_and_backends_agree() -> None:
    law = PDLaw(6, 1e-3, ROBOT.torque_limit_nm)
    base = simulate(ROBOT, FeedbackController(law), SHORT[:1], SimConfig(substeps=2))
    fine = simulate(ROBOT, FeedbackController(law), SHORT[:1], SimConfig(substeps=8))
    own = simulate(ROBOT, FeedbackController(law), SHORT[:1], SimConfig(plant_backend="rne"))
    assert np.abs(base.q - fine.q).max() < 1e-6
    assert np.abs(base.q - own.q).max() < 1e-9


def test_torque_is_saturated_and_limits_reported() -> None:
    class Huge(GravityCompensation):
        def __call__(self, t_s, q, qd, q_d, qd_d, qdd_d):
            return np.full_like(q, 1e6)

    traj = simulate(ROBOT, Huge(), [replace(SHORT[0], duration_s=0.2)])
    assert np.abs(traj.tau[0]).max(axis=0) == pytest.approx(ROBOT.torque_limit_nm)
    assert not traj.within_limits[0]  # full torque on a 1e-4 kg m^2 wrist exceeds 0.81 pi rad/s at once


def test_mismatch_changes_the_plant_only() -> None:
    law = PDLaw(6, 1e-3, ROBOT.torque_limit_nm)
    heavy = [replace(c, mismatch=Mismatch(payload_kg=0.5, viscous_friction_nm_s=0.1)) for c in SHORT]
    nominal = simulate(ROBOT, FeedbackController(law), SHORT)
    loaded = simulate(ROBOT, FeedbackController(law), heavy)
    assert np.abs(nominal.q - loaded.q).max() > 1e-3


def test_mixed_batches_are_refused() -> None:
    mixed = [SHORT[0], replace(SHORT[1], mismatch=Mismatch(payload_kg=1.0))]
    with pytest.raises(ModelInputError, match="share duration, disturbance and mismatch"):
        simulate(ROBOT, FeedbackController(PDLaw(6, 1e-3, ROBOT.torque_limit_nm)), mixed)
