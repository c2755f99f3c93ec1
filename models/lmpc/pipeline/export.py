"""Stage ``export``: the policy bundles (<bundles>/<robot>/<law>/) with their training provenance,
from the augment stage's emulators when it ran, else from the train stage's."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from hil_runtime.bundle_schema import FEATURE_SETS, GUARD_FEATURES
from models.feedback import make_law
from models.lmpc.dataset import git_commit, load_raw_dataset
from models.lmpc.pipeline.config import PipelineConfig
from models.lmpc.pipeline.labeling import load_labels
from models.robots import load_robot


def export_deployed(
    config: PipelineConfig,
    robot: Any,
    law_name: str,
    result: dict[str, Any],
    out: Path,
    training: dict[str, Any],
    validation: dict[str, Any],
    parity_inputs: np.ndarray | None = None,
) -> dict[str, Any]:
    import torch

    from models.lmpc.bundle_export import export_bundle
    from models.lmpc.emulator import Emulator

    spec = config.dataset
    if "box_margin" in result:  # chosen per law by select_margins
        config = replace(config, box_margin=result["box_margin"])
    width = len(FEATURE_SETS[config.feature_set]) * robot.n_joints
    emulator = Emulator(width, robot.n_joints, config.deploy_hidden)
    emulator.load_state_dict({k: torch.as_tensor(v) for k, v in result["state_dict"].items()})
    training = {
        "gain_set": spec.gain_set,
        **training,
        "trust": {
            "residual_percentile": config.residual_percentile,
            "box": result.get("box_kind", "on_policy"),
            "box_margin": config.box_margin,
            "box_note": "on_policy: min/max of the guard features over the on-policy training states; labeled: "
            "those and the HMPC-labeled D_sample states; chosen per law (augment stage, docs/lmpc.md)",
        },
    }
    return export_bundle(
        out,
        make_law(law_name, robot, spec.period_s, spec.gain_set),
        robot,
        emulator,
        training,
        validation,
        trust_region=result["box"],
        parity_inputs=parity_inputs,
        residual=True,
        residual_bound_nm=result["residual_bound_nm"],
        box_margin=config.box_margin,
        feature_set=config.feature_set,
    )


def stage_export(
    config: PipelineConfig,
    work: Path,
    trained: dict[str, Any],
    bundles: Path,
    strategy: str = "optimal",
    seed: int | None = None,
) -> dict[str, Any]:
    import torch

    from models.lmpc.bundle_export import export_bundle
    from models.lmpc.emulator import Emulator

    robot = load_robot(config.dataset.robot)
    raw = load_raw_dataset(work / "raw.h5", config.laws)
    labels_manifest, labels = load_labels(work / "labels.h5")
    seed = config.seeds[0] if seed is None else seed
    augmented = None
    if (work / "augmented.pkl").is_file() and config.rollout_conditions > 0:
        import pickle

        with open(work / "augmented.pkl", "rb") as handle:
            augmented = pickle.load(handle)
    out = {}
    for law_name in config.laws:
        run = next(
            r for r in trained["runs"] if r["law"] == law_name and r["strategy"] == strategy and r["seed"] == seed
        )
        if augmented is not None:
            run = {
                **run,
                "state_dict": augmented[law_name]["state_dict"],
                "augmented_summary": augmented[law_name]["summary"],
            }
        law = make_law(law_name, robot, config.dataset.period_s, config.dataset.gain_set)
        rows, lab = raw.laws[law_name], labels[law_name]
        x_train = rows.features(GUARD_FEATURES)[lab.sets[strategy]]  # the trust box is over the guard features
        parity = rows.take(lab.sets["test"][:256])
        parity_x = np.concatenate([parity.q, parity.qd, parity.q_d, parity.qd_d, parity.qdd_d, parity.law_state], 1)
        training = {
            "dataset": {
                "file": "raw.h5",
                "spec": raw.manifest["spec"],
                "git_commit": raw.manifest["git_commit"],
                "created": raw.manifest["created"],
            },
            "labels": {
                "labeler": labels_manifest["labeler"],
                "hmpc_options": labels_manifest["hmpc_options"],
                "status_counts": np.bincount(lab.status, minlength=4).tolist(),
            },
            "sampling": {"strategy": strategy, "samples": int(lab.sets[strategy].size), "theorem2": lab.theorem2},
            "emulator": run.get("augmented_summary", run["summary"]),
            "augmentation": None
            if augmented is None
            else {
                "hmpc_rollout_conditions": config.rollout_conditions,
                "rollout_duration_s": config.rollout_duration_s,
                "dagger_rounds": config.dagger_rounds,
                "dagger_conditions": config.dagger_conditions,
                "repeat": config.augment_repeat,
                "samples": augmented[law_name].get("samples"),
                "feature_set": config.feature_set,
                "note": "D_sample (Theorem 2) + HMPC closed-loop states + DAgger rounds, residual target "
                "tau* - tau_fb, Theorem 2 region weights on the on-policy samples; docs/lmpc.md",
            },
            "seed": seed,
            "gain_set": config.dataset.gain_set,
            "git_commit": git_commit(),
        }
        validation = {
            "val_mse_normalized": run["summary"]["best_val_mse_normalized"],
            "val_rmse_nm": run["summary"]["val_rmse_nm"],
            "test_mse_normalized": run["test_mse"],
            "test_set": "uniform over held-out conditions",
        }
        if augmented is not None:
            validation["note"] = (
                "val/test MSE above: the paper-recipe emulator of the train stage; the deployed one's "
                "validation is training.emulator (residual target, normalized by its RMS)"
            )
            manifest = export_deployed(
                config,
                robot,
                law_name,
                augmented[law_name],
                bundles / robot.name / law_name,
                {k: v for k, v in training.items() if k != "gain_set"},
                validation,
                parity_x,
            )
        else:
            emulator = Emulator(5 * robot.n_joints, robot.n_joints, config.train.hidden)
            emulator.load_state_dict({k: torch.as_tensor(v) for k, v in run["state_dict"].items()})
            manifest = export_bundle(
                bundles / robot.name / law_name,
                law,
                robot,
                emulator,
                training,
                validation,
                trust_region=(x_train.min(0), x_train.max(0)),
                parity_inputs=parity_x,
                box_margin=config.box_margin,
            )
        out[law_name] = {
            "path": str(bundles / robot.name / law_name),
            "onnx_vs_torch_max_abs_nm": manifest["validation"]["onnx_vs_torch_max_abs_nm"],
        }
    return out
