"""Realism profiles on arms of any joint count (issue 25, docs/realism.md "Any arm"): the shipped
profiles give ur5_paper its listed values bit for bit and every other arm per-joint values by the
torque-limit rule; explicit lists of the wrong length stay one-line errors naming file and field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim_target.realism import RealismError
from sim_target.realism_profiles import load_realism, scale_by_torque_limit

PERIOD_S = 1e-3
UR5_PAPER_NM = np.array([102.0, 102.0, 66.0, 34.0, 34.0, 34.0])
UR5_NM = np.array([150.0, 150.0, 150.0, 28.0, 28.0, 28.0])
PANDA_NM = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])


def test_scale_by_torque_limit_closed_form() -> None:
    values = np.array([1.5, 1.5, 1.0, 0.3, 0.3, 0.3])
    # on the reference arm itself: its own list, bit for bit
    np.testing.assert_array_equal(scale_by_torque_limit(values, UR5_PAPER_NM, UR5_PAPER_NM), values)
    # between two reference classes the value per N·m is interpolated linearly in the limit
    per_nm = 1.0 / 66 + (87 - 66) / (102 - 66) * (1.5 / 102 - 1.0 / 66)
    # beyond the reference's range it is held: proportional to the limit
    out = scale_by_torque_limit(values, UR5_PAPER_NM, np.array([87.0, 12.0, 150.0, 34.0]))
    np.testing.assert_allclose(out, [87 * per_nm, 0.3 * 12 / 34, 1.5 * 150 / 102, 0.3], rtol=1e-12)
    with pytest.raises(ValueError, match="34 N·m"):
        scale_by_torque_limit(np.array([1.0, 0.3, 0.4]), np.array([102.0, 34.0, 34.0]), PANDA_NM)


@pytest.mark.parametrize("name", ["realistic", "harsh"])
def test_shipped_profiles_keep_ur5_papers_values(name: str) -> None:
    world = load_realism(name, 6, PERIOD_S, PERIOD_S / 2, UR5_PAPER_NM)
    k = 2.0 if name == "harsh" else 1.0  # harsh: twice the realistic friction
    np.testing.assert_array_equal(world.plant.viscous_friction_nm_s_per_rad, k * np.array([1.0, 1, 0.6, 0.2, 0.2, 0.2]))
    np.testing.assert_array_equal(world.plant.coulomb_friction_nm, k * np.array([1.5, 1.5, 1.0, 0.3, 0.3, 0.3]))
    np.testing.assert_array_equal(world.plant.stribeck_friction_nm, k * np.array([0.5, 0.5, 0.3, 0.1, 0.1, 0.1]))
    e = 0.2 if name == "harsh" else 0.05
    np.testing.assert_array_equal(world.plant.inertia_scale, np.resize([1 + e, 1 - e], 6))


def test_realistic_binds_to_the_panda_and_the_ur5_by_the_rule() -> None:
    panda = load_realism("realistic", 7, PERIOD_S, PERIOD_S / 2, PANDA_NM)
    assert panda.n_joints == 7
    shoulder = 87 * (1.0 / 66 + (87 - 66) / 36 * (1.5 / 102 - 1.0 / 66))
    np.testing.assert_allclose(panda.plant.coulomb_friction_nm, [shoulder] * 4 + [0.3 * 12 / 34] * 3, rtol=1e-12)
    np.testing.assert_array_equal(panda.plant.inertia_scale, [1.05, 0.95, 1.05, 0.95, 1.05, 0.95, 1.05])
    np.testing.assert_allclose(panda.actuation.torque_quantum_nm, 0.5 * PANDA_NM / 1000)  # 1 per mille of rated
    assert np.all(panda.sensing.encoder_counts_per_rev == 2**19)
    ur5 = load_realism("realistic", 6, PERIOD_S, PERIOD_S / 2, UR5_NM)
    np.testing.assert_allclose(ur5.plant.viscous_friction_nm_s_per_rad, [150 / 102] * 3 + [0.2 * 28 / 34] * 3)


BAD = [
    # an explicit list is for one joint count: still refused on another arm
    ("plant: {coulomb_friction_nm: [1.5, 1.5, 1.0, 0.3, 0.3, 0.3]}\n", "plant.coulomb_friction_nm", "7"),
    ("plant: {coulomb_friction_nm: {scaled: [1, 2]}}\n", "plant.coulomb_friction_nm", "reference_torque_limit_nm"),
    (
        "reference_torque_limit_nm: [100, 50]\nplant: {coulomb_friction_nm: {scaled: [1, 2, 3]}}\n",
        "plant.coulomb_friction_nm",
        "expected 2",
    ),
    (
        "reference_torque_limit_nm: [50, 50]\nplant: {viscous_friction_nm_s_per_rad: {scaled: [1, 2]}}\n",
        "plant.viscous_friction_nm_s_per_rad",
        "50 N·m",
    ),
    ("reference_torque_limit_nm: [100, 0]\n", "reference_torque_limit_nm", ""),
    ("plant: {inertia_scale: {repeat: []}}\n", "plant.inertia_scale", ""),
    ("sensing: {encoder_noise_rad: {scaled: [1.0e-5]}}\n", "sensing.encoder_noise_rad", ""),  # not a torque
]


@pytest.mark.parametrize(("text", "field", "detail"), BAD)
def test_bad_any_arm_profiles_one_line(tmp_path: Path, text: str, field: str, detail: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(RealismError) as info:
        load_realism(path, 7, PERIOD_S, PERIOD_S / 2, PANDA_NM)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message and field in message and detail in message, message
    assert info.value.exit_code == 2


def test_the_panda_runs_under_realistic_in_the_simulator() -> None:
    """The bound profile drives the models simulator on the 7-joint arm (it was refused before)."""
    from dataclasses import replace

    from models.conditions import load_conditions
    from models.experiment import ExperimentConfig, realism_spec
    from models.feedback import make_law
    from models.modes import make_controller
    from models.robots import load_robot
    from models.sim import SimConfig, simulate

    robot = load_robot("panda")
    world = realism_spec(ExperimentConfig(realism="realistic"), robot)
    condition = replace(load_conditions(None, robot=robot)[0], duration_s=0.05)
    law = make_law("pd", robot, PERIOD_S, "designed")
    real = simulate(robot, make_controller("fb", law, robot), [condition], SimConfig(), realism=world)
    ideal = simulate(robot, make_controller("fb", law, robot), [condition], SimConfig())
    assert np.all(np.isfinite(real.q)) and real.q.shape[-1] == 7
    assert np.abs(real.tau - ideal.tau).max() > 1e-3  # the world is applied
