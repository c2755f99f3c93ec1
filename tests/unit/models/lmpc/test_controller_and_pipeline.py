"""LMPC controller (a bundle through hil_runtime.bundle in the simulator) and a tiny pipeline run."""

from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from hil_runtime.bundle import BundleError  # noqa: E402
from models.conditions import load_conditions  # noqa: E402
from models.feedback import make_law  # noqa: E402
from models.lmpc import make_lmpc_controller  # noqa: E402
from models.lmpc.bundle_export import export_bundle  # noqa: E402
from models.lmpc.emulator import Emulator, TrainConfig, train_emulator  # noqa: E402
from models.robots import load_robot  # noqa: E402
from models.sim import FeedbackController, SimConfig, simulate  # noqa: E402

if TYPE_CHECKING:
    from models.lmpc.pipeline import PipelineConfig


class IdentityOnFeedback(Emulator):
    """An 'emulator' that returns tau_fb: LMPC must then reproduce FB exactly."""

    def forward(self, s: Any) -> Any:  # torch.Tensor (torch is imported by importorskip)
        return s[:, 24:30]


@pytest.mark.parametrize("law_name", ["adrc", "mrac"])
def test_lmpc_with_a_feedback_emulator_reproduces_the_feedback_run(tmp_path, law_name):
    robot = load_robot("ur5_paper")
    law = make_law(law_name, robot, 1e-3)
    export_bundle(tmp_path / law_name, law, robot, IdentityOnFeedback(30, 6, (4,)), {}, {})
    condition = replace(load_conditions()[0], duration_s=0.3)
    lmpc = make_lmpc_controller(law, robot, bundle_dir=tmp_path)
    a = simulate(robot, lmpc, [condition, condition], SimConfig())
    b = simulate(robot, FeedbackController(make_law(law_name, robot, 1e-3)), [condition, condition], SimConfig())
    np.testing.assert_allclose(a.q, b.q, atol=1e-9)
    single = make_lmpc_controller(law, robot, bundle_dir=tmp_path)
    c = simulate(robot, single, [condition], SimConfig())  # the runtime's single-row path
    np.testing.assert_allclose(c.q[0], b.q[0], atol=1e-9)
    assert len(single.cycle_times_s) == 300
    assert single.trust_counters() == {
        "cycles": 300,
        "fallback_cycles": [0],
        "blended_cycles": [0],
        "clamped_cycles": [0],
    }


def test_a_bundle_with_other_law_parameters_is_refused(tmp_path):
    robot = load_robot("ur5_paper")
    export_bundle(tmp_path / "adrc", make_law("adrc", robot, 1e-3, "paper"), robot, Emulator(30, 6, (4,)), {}, {})
    with pytest.raises(BundleError, match="parameters differ"):
        make_lmpc_controller(make_law("adrc", robot, 1e-3, "stabilized"), robot, bundle_dir=tmp_path)


def test_training_is_seeded_and_learns_a_smooth_map():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2000, 30))
    y = np.tanh(x[:, :6]) * 10 + x[:, 24:30]
    config = TrainConfig(hidden=(32, 32), max_epochs=25, patience=5, seed=3)
    a, b = train_emulator(x, y, config), train_emulator(x, y, config)
    assert a.val_mse == b.val_mse
    assert a.best_val_mse < 0.1 * a.val_mse[0]


def _tiny_pipeline_config(**augment: Any) -> "PipelineConfig":
    """The PD law on 90 labelled samples of a 4-condition dataset, a 16-unit network, 3 epochs; the
    augment stage's options as given."""
    from models.lmpc.dataset import RawDatasetSpec
    from models.lmpc.pipeline import PipelineConfig

    return PipelineConfig(
        dataset=RawDatasetSpec(laws=("pd",), conditions=4, duration_s=5.0, stride=50, chunks=1),
        budget=90,
        pool_conditions=3,
        test_per_law=30,
        seeds=(0,),
        train=TrainConfig(hidden=(16,), max_epochs=3, patience=2),
        label_chunk=128,
        workers=1,
        **augment,
    )


def test_tiny_pipeline_end_to_end_with_the_hmpc_labeler(tmp_path):
    from hil_runtime.bundle import PolicyBundle
    from models.executors import SerialExecutor
    from models.lmpc.pipeline import run_pipeline

    config = _tiny_pipeline_config(rollout_conditions=0)
    summary = run_pipeline(config, tmp_path / "work", tmp_path / "bundles", executor=SerialExecutor())
    assert "augment" not in summary["wall_s"]
    assert set(summary["wall_s"]) >= {"dataset", "label", "train", "export", "total"}
    np.testing.assert_allclose(sum(summary["theorem2"]["pd"]["weights"]), 1.0)
    bundle = PolicyBundle.load(tmp_path / "bundles" / "ur5_paper" / "pd", expected_joints=6, expected_period_s=1e-3)
    assert bundle.manifest.training["sampling"]["samples"] == 90
    assert bundle.manifest.training["labels"]["labeler"] == "hmpc_labeler"
    assert (tmp_path / "work" / "sampling_curves.png").stat().st_size > 1000


def test_augment_stage_hmpc_rollouts_and_a_dagger_round(tmp_path):
    """Beyond the paper: HMPC closed loop on one 2.5 s condition, one DAgger round, residual + trust region."""
    from hil_runtime.bundle import PolicyBundle
    from models.executors import SerialExecutor
    from models.lmpc.pipeline import run_pipeline

    config = _tiny_pipeline_config(
        rollout_conditions=1,
        rollout_duration_s=2.5,
        rollout_stride=25,
        dagger_rounds=1,
        dagger_conditions=1,
        dagger_duration_s=0.5,
        dagger_states_per_law=50,
        augment_epochs=3,
        deploy_hidden=(16,),
        on_policy_max_error_rad=10.0,
        trust_candidates=(("on_policy", 0.5), ("labeled", 0.1)),
        selection_duration_s=0.3,
    )
    summary = run_pipeline(config, tmp_path / "work", tmp_path / "bundles", executor=SerialExecutor())
    assert summary["augment"]["rollout_states_per_law"]["pd"] == 100
    assert summary["augment"]["dagger"][0]["pd"]["labeled"] > 0
    bundle = PolicyBundle.load(tmp_path / "bundles" / "ur5_paper" / "pd")
    assert bundle.manifest.training["augmentation"]["hmpc_rollout_conditions"] == 1
    assert bundle.manifest.emulator.residual and bundle.manifest.emulator.feature_set == "ref"
    trust = bundle.manifest.trust_region
    assert trust is not None and trust.residual_bound_nm is not None
    assert len(trust.feature_low) == 36 and len(trust.residual_bound_nm) == 6
    chosen = summary["augment"]["margin_selection"]["pd"]["chosen"]
    assert [bundle.manifest.training["trust"]["box"], trust.box_margin] == list(chosen)
