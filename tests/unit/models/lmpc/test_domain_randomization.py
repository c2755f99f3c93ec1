"""Domain randomization and envelope conditions in the structured LMPC's training data (docs/lmpc.md §12)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from models.lmpc.structured import StructuredConfig
from models.lmpc.structured.data import _data_key, rollout_groups
from models.lmpc.structured.randomization import (
    ENCODER_NOISE_TOP_RAD,
    INERTIA_ERROR,
    VELOCITY_NOISE_TOP_RAD_S,
    randomized_realism,
)
from models.lmpc.structured.run import training_conditions
from models.robots import load_robot
from models.sim import batch_key
from sim_target.realism import RealismSpec
from sim_target.realism_profiles import load_realism


def _realistic(n: int = 6) -> RealismSpec:
    robot = load_robot("ur5_paper")
    return load_realism("realistic", n, 1e-3, 5e-4, robot.torque_limit_nm)


def test_a_draw_is_seeded_within_its_ranges_and_differs_from_another() -> None:
    base = _realistic()
    a, a2, b = randomized_realism(base, 1), randomized_realism(base, 1), randomized_realism(base, 2)
    assert np.array_equal(a.sensing.encoder_noise_rad, a2.sensing.encoder_noise_rad) and a.seed == 1
    assert not np.array_equal(a.sensing.encoder_noise_rad, b.sensing.encoder_noise_rad)
    for draw in (a, b):
        s, p = draw.sensing, draw.plant
        assert np.all(s.encoder_noise_rad >= base.sensing.encoder_noise_rad * (1 - 1e-9))
        assert np.all(s.encoder_noise_rad <= ENCODER_NOISE_TOP_RAD)
        assert np.all(s.velocity_noise_rad_s <= VELOCITY_NOISE_TOP_RAD_S)
        assert s.delay_periods in (base.sensing.delay_periods, base.sensing.delay_periods + 1)
        ratio = p.coulomb_friction_nm / base.plant.coulomb_friction_nm
        assert np.all((ratio >= 0.5) & (ratio <= 1.5))
        assert np.all(np.abs(p.mass_scale - 1.0) <= INERTIA_ERROR + 1e-12)
        assert s.encoder_counts_per_rev is base.sensing.encoder_counts_per_rev  # the encoder stays the drive's
        assert not draw.is_ideal


def test_training_conditions_rotate_over_the_draws_and_batch_by_disturbance() -> None:
    robot = load_robot("ur5_paper")
    config = StructuredConfig(train_conditions=4, envelope_conditions=6, train_realism="realistic", realism_draws=3)
    conditions = training_conditions(robot, config, 4, 7101, "T")
    assert len(conditions) == 10 and sum(c.name.startswith("TE") for c in conditions) == 6
    assert all(c.duration_s == config.duration_s for c in conditions)
    groups = rollout_groups(config, conditions, robot)
    assert sum(len(members) for members, _ in groups) == 10
    assert len({world.name for _, world in groups}) == 3  # every draw used
    for members, _ in groups:  # one simulator batch each
        assert len({batch_key(c) for c in members}) == 1
    mixed = rollout_groups(replace(config, realism_draws=2, ideal_draws=2), conditions[:4], robot)
    assert len(mixed) == 4 and sum(world is None for _, world in mixed) == 2  # the nominal plant among the draws
    ideal = rollout_groups(StructuredConfig(train_conditions=4), conditions[:4], robot)
    assert len(ideal) == 1 and ideal[0][1] is None


def test_the_cache_key_changes_with_the_world_and_keeps_old_caches() -> None:
    plain = StructuredConfig()
    assert "train_realism" not in _data_key(plain)  # caches made before the option stay valid
    assert _data_key(plain) != _data_key(StructuredConfig(train_realism="realistic"))
    assert _data_key(StructuredConfig(train_realism="realistic")) != _data_key(
        StructuredConfig(train_realism="realistic", realism_draws=2)
    )
    assert _data_key(plain) != _data_key(StructuredConfig(envelope_conditions=2))
    randomized = StructuredConfig(train_realism="realistic")
    assert "ideal_draws" not in _data_key(randomized)  # keyed only when set: earlier randomized caches stay valid
    assert _data_key(randomized) != _data_key(replace(randomized, ideal_draws=1))


def test_randomized_rollouts_export_a_bundle_whose_box_covers_the_envelope_data(tmp_path: Path) -> None:
    from hil_runtime.bundle import PolicyBundle
    from models.hmpc.config import formulation_options
    from models.lmpc.structured import run_structured
    from models.lmpc.structured.data import collect, features

    config = StructuredConfig(  # the deployable HMPC (the absolute-cost one's deadbeat gains blow up on noise)
        hmpc_options=formulation_options("deployable", "ur5_paper"),
        laws=("pd",),
        train_conditions=1,
        envelope_conditions=1,
        train_realism="realistic",
        realism_draws=2,
        duration_s=0.3,
        stride=10,
        residual_epochs=2,
        physics_steps=100,
        perturb_error_rad=1e-3,
        perturb_rate_rad_s=2e-2,
        c_fixed=-1.0,
    )
    run_structured(config, tmp_path / "bundles", tmp_path / "work", log=lambda _: None)
    bundle = PolicyBundle.load(tmp_path / "bundles" / "ur5_paper" / "pd")
    assert bundle.manifest.training["config"]["train_realism"] == "realistic"
    robot = load_robot("ur5_paper")
    conditions = training_conditions(robot, config, 1, config.train_seed, "T")
    rows = collect(config, conditions)["pd"]
    ideal = collect(replace(config, train_realism=None), conditions)["pd"]
    assert rows["q"].shape == ideal["q"].shape and not np.allclose(rows["q"], ideal["q"])  # the world was applied
    q = features(rows)[:, : robot.n_joints]
    region = bundle.manifest.trust_region
    assert region is not None
    box = np.asarray(region.feature_low), np.asarray(region.feature_high)
    assert np.all(q >= box[0][: robot.n_joints] - 1e-9) and np.all(q <= box[1][: robot.n_joints] + 1e-9)


@pytest.mark.parametrize("field, value", [("realism_draws", 0), ("envelope_conditions", -1), ("ideal_draws", -1)])
def test_bad_randomization_settings_are_refused(field: str, value: int) -> None:
    from models.errors import ModelInputError

    with pytest.raises(ModelInputError, match=field):
        StructuredConfig(**{field: value})
