"""The pybullet plant: faithful dynamics (no hidden motors, damping or phantom masses), brake,
measurement, payload and impulse faults. The project's dynamics (models.dynamics) is the oracle."""

from __future__ import annotations

import numpy as np
import pybullet
import pytest

from models.dynamics import make_dynamics
from models.robots import load_robot
from sim_target.checks import check_plant
from sim_target.plant import (
    PAPER_DISTURBANCE,
    JointState,
    PlantError,
    PybulletPlant,
    TorqueImpulse,
    load_arm,
)

Q0 = np.array([0.3, -0.5, 0.8, -0.4, 0.5, 0.2])
FREE = np.zeros(6, dtype=bool)
ALL_BRAKED = np.ones(6, dtype=bool)


@pytest.fixture(scope="module")
def robot():
    return load_robot("ur5_paper")


@pytest.fixture
def plant():
    with PybulletPlant(period_s=1e-3, substeps=4, initial_position_rad=Q0) as p:
        yield p


def test_implements_the_target_plant_protocol(plant: PybulletPlant) -> None:
    check_plant(plant)  # the public conformance check (sim_target.checks), leaves it reset
    assert plant.n_joints == 6
    state = plant.state()
    assert isinstance(state, JointState)
    np.testing.assert_allclose(state.position_rad, Q0, atol=1e-12)
    assert state.time_s == 0.0


def test_massless_urdf_links_stay_massless() -> None:
    # pybullet gives a link without <inertial> 1 kg; ur5_paper's flange has none.
    client = pybullet.connect(pybullet.DIRECT)
    try:
        from models.robots import urdf_path

        body = load_arm(client, urdf_path("ur5_paper"))
        names = [pybullet.getJointInfo(body, j, physicsClientId=client)[12].decode() for j in range(7)]
        flange = names.index("flange")
        assert pybullet.getDynamicsInfo(body, flange, physicsClientId=client)[0] == 0.0
    finally:
        pybullet.disconnect(client)


def test_gravity_compensation_holds_the_arm_still(plant: PybulletPlant, robot) -> None:
    # Fails if any phantom mass, damping or inertia differs from the project's model.
    dyn = make_dynamics(robot)
    for _ in range(500):
        state = plant.step(dyn.gravity(plant.state().position_rad), FREE)
    np.testing.assert_allclose(state.position_rad, Q0, atol=1e-9)


def test_a_free_joint_coasts_without_damping_or_motor(plant: PybulletPlant) -> None:
    # Brake every joint but the vertical pan axis, spin it up, then let it coast: its speed must
    # stay constant (pybullet's default damping 0.04 or its velocity motor would slow it).
    pan_free = np.array([False, True, True, True, True, True])
    spin_up = np.array([2.0, 0, 0, 0, 0, 0])
    for _ in range(50):
        plant.step(spin_up, pan_free)
    speed_rad_s = plant.state().velocity_rad_s[0]
    assert speed_rad_s > 0.1
    for _ in range(1000):
        state = plant.step(np.zeros(6), pan_free)
    # 1e-5: the braked joints yield by ~1e-8 rad; damping 0.04 would cost several per cent.
    assert state.velocity_rad_s[0] == pytest.approx(speed_rad_s, rel=1e-5)


def test_brake_holds_joints_and_releases(plant: PybulletPlant) -> None:
    half = np.array([True, False, True, False, True, False])
    for _ in range(1000):
        state = plant.step(np.full(6, 5.0), half)
    np.testing.assert_allclose(state.position_rad[half], Q0[half], atol=1e-6)
    assert np.all(np.abs(state.position_rad[~half] - Q0[~half]) > 1e-2)  # the others moved
    np.testing.assert_array_equal(state.torque_nm[half], 0.0)  # a braked drive delivers no torque
    braked_at = plant.state().position_rad.copy()
    for _ in range(100):
        state = plant.step(np.zeros(6), FREE)
    assert abs(state.position_rad[2] - braked_at[2]) > 1e-3  # the elbow falls once released


def test_brake_re_engages_where_the_joint_is(plant: PybulletPlant) -> None:
    for _ in range(100):
        plant.step(np.zeros(6), FREE)
    where = plant.state().position_rad.copy()
    for _ in range(500):
        state = plant.step(np.zeros(6), ALL_BRAKED)
    np.testing.assert_allclose(state.position_rad, where, atol=2e-3)  # stops within its momentum
    settled = state.position_rad.copy()
    for _ in range(500):
        state = plant.step(np.zeros(6), ALL_BRAKED)
    np.testing.assert_allclose(state.position_rad, settled, atol=1e-7)


def test_torque_is_clipped_to_the_effort_limit(plant: PybulletPlant) -> None:
    state = plant.step(np.array([500.0, -500.0, 1.0, 0.0, 0.0, 0.0]), FREE)
    np.testing.assert_array_equal(state.torque_nm, [102.0, -102.0, 1.0, 0.0, 0.0, 0.0])


def test_time_counts_periods(plant: PybulletPlant) -> None:
    for _ in range(2500):
        state = plant.step(np.zeros(6), ALL_BRAKED)
    assert state.time_s == 2.5
    assert plant.reset().time_s == 0.0


def test_same_inputs_give_identical_runs() -> None:
    def run() -> np.ndarray:
        with PybulletPlant(initial_position_rad=Q0, encoder_noise_rad=1e-4, seed=7) as p:
            return np.array([p.step(np.sin(np.arange(6) + 0.01 * k), FREE).position_rad for k in range(300)])

    np.testing.assert_array_equal(run(), run())


def test_encoder_noise_is_seeded_and_only_in_the_measurement() -> None:
    with PybulletPlant(initial_position_rad=Q0, encoder_noise_rad=1e-3, seed=3) as p:
        samples = np.array([p.step(np.zeros(6), ALL_BRAKED).position_rad for _ in range(2000)])
        assert np.array_equal(p.state().position_rad, samples[-1])  # state() repeats the sample
        np.testing.assert_allclose(p.true_state().position_rad, Q0, atol=1e-6)
    errors = samples - Q0
    assert errors.std() == pytest.approx(1e-3, rel=0.05)
    assert abs(errors.mean()) < 1e-4
    with PybulletPlant(initial_position_rad=Q0, encoder_noise_rad=1e-3, seed=4) as other:
        assert not np.array_equal(other.step(np.zeros(6), ALL_BRAKED).position_rad, samples[0])


def test_payload_sits_on_the_flange(plant: PybulletPlant, robot) -> None:
    # Gravity torque for the model carrying 2 kg at the flange holds the plant carrying it.
    loaded = make_dynamics(robot.with_payload(2.0))
    plant.set_payload(2.0)
    for _ in range(300):
        state = plant.step(loaded.gravity(plant.state().position_rad), FREE)
    np.testing.assert_allclose(state.position_rad, Q0, atol=1e-9)
    plant.set_payload(0.0)
    for _ in range(300):
        state = plant.step(loaded.gravity(plant.state().position_rad), FREE)
    assert np.abs(state.position_rad - Q0).max() > 1e-2  # too much torque for the bare arm


def test_impulse_changes_momentum_by_its_impulse(plant: PybulletPlant, robot) -> None:
    dyn = make_dynamics(robot)
    impulse = TorqueImpulse(torque_nm=(0.1, 0.1, 0.05, 0.05, 0.01, 0.01), start_s=0.0105, duration_s=5e-4)
    plant.add_impulse(impulse)
    for _ in range(10):
        state = plant.step(dyn.gravity(plant.state().position_rad), FREE)
    np.testing.assert_allclose(state.velocity_rad_s, 0.0, atol=1e-12)  # nothing before 10.5 ms
    command_nm = dyn.gravity(plant.state().position_rad)
    state = plant.step(command_nm, FREE)
    expected = np.linalg.solve(dyn.mass_matrix(Q0), np.asarray(impulse.torque_nm) * 5e-4)
    np.testing.assert_allclose(state.velocity_rad_s, expected, rtol=0.02, atol=1e-5)
    np.testing.assert_array_equal(state.torque_nm, command_nm)  # the drive measures its own torque only


def test_mean_torque_of_a_pulse_over_a_period() -> None:
    pulse = TorqueImpulse(torque_nm=(10.0,), start_s=2.0, duration_s=1.5e-3)
    assert pulse.mean_torque_nm(1.999, 1e-3)[0] == 0.0
    assert pulse.mean_torque_nm(2.000, 1e-3)[0] == pytest.approx(10.0)
    assert pulse.mean_torque_nm(2.001, 1e-3)[0] == pytest.approx(5.0)
    assert pulse.mean_torque_nm(2.002, 1e-3)[0] == 0.0
    assert PAPER_DISTURBANCE.torque_nm == (1.0, 1.0, 5.0, 5.0, 10.0, 10.0)
    assert PAPER_DISTURBANCE.start_s == 2.0


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"period_s": 0.0}, "period_s"),
        ({"substeps": 0}, "substeps"),
        ({"initial_position_rad": [0.0] * 5}, "initial_position_rad"),
    ],
)
def test_bad_parameters_are_user_errors(kwargs: dict, field: str) -> None:
    with pytest.raises(PlantError, match=field) as info:
        PybulletPlant(**kwargs)
    assert info.value.exit_code == 2


def test_bad_step_inputs_are_refused(plant: PybulletPlant) -> None:
    with pytest.raises(PlantError, match="torque_nm"):
        plant.step(np.zeros(5), FREE)
    with pytest.raises(PlantError, match="torque_nm"):
        plant.step(np.full(6, np.nan), FREE)
    with pytest.raises(PlantError, match="brake_engaged"):
        plant.step(np.zeros(6), np.zeros(3, dtype=bool))
