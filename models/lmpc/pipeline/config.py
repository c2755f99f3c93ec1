"""The LMPC pipeline's settings (one frozen config, read by every stage) and its progress hook."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

from models.executors import DEFAULT_EXECUTOR
from models.lmpc.dataset import RawDatasetSpec
from models.lmpc.emulator import TrainConfig

Progress = Callable[[str, int], Callable[[int], None]]


@dataclass(frozen=True)
class PipelineConfig:
    dataset: RawDatasetSpec = RawDatasetSpec()
    budget: int = 100_000  # labeled samples over all laws (paper: 100,000 of 600,000)
    pool_conditions: int = 90  # conditions the samplers draw from; the rest give the test set
    test_per_law: int = 2000
    lipschitz_delta: str | tuple[float, ...] = (0.0, 0.0, 0.0)  # or "estimate"
    epsilon: float = 1e-9
    power: float = 1.0
    seeds: tuple[int, ...] = (0, 1, 2)
    train: TrainConfig = TrainConfig()
    label_chunk: int = 2048  # states per progress update
    # Beyond the paper (docs/lmpc.md): the deployed emulators (augment stage): residual target,
    # HMPC closed-loop rollouts + DAgger rounds, trust region.
    rollout_conditions: int = 60  # pool conditions run under the HMPC itself (0: skip the stage)
    rollout_duration_s: float = 3.0  # 0 .. 3 s: the start-up transient and the disturbance at 2 s
    rollout_stride: int = 3
    rollout_initial_state: str = (
        "reference"  # start on the reference, as the paper's conditions do ("home": from zeros)
    )
    dagger_rounds: int = 0  # the shipped bundles: 0 (docs/lmpc.md); --dagger-rounds N
    dagger_conditions: int = 16  # pool conditions (after the rollout ones) run under the intermediate LMPC
    dagger_duration_s: float = 3.0
    dagger_states_per_law: int = 4000
    augment_repeat: int = 2  # base repeat of the on-policy (rollout, DAgger) samples in training
    augment_epochs: int = 100
    deploy_hidden: tuple[int, ...] = (128, 128)
    feature_set: str = "ref"  # hil_runtime.bundle.FEATURE_SETS; "ref" = (q_d, qd_d, qdd_d), docs/lmpc.md
    deploy_use_d_sample: bool = False  # also train the deployed emulator on D_sample (feedback-only states)
    on_policy_max_error_rad: float = 0.0175  # on-policy samples kept where every |e_j| is below this (1 deg)
    residual_percentile: float = 100.0  # trust region: per-joint bound on |tau_L - tau_fb|
    box_margin: float = (
        0.5  # trust region: alpha fades from 1 at the box edge to 0 at this fraction of its range outside
    )
    # per law, the trust region (box, margin) is chosen among these by closed-loop runs on pool
    # conditions (never the paper's); box "on_policy": the on-policy training states, "labeled": those
    # and every HMPC-labeled D_sample state (feedback-only states with errors of degrees)
    trust_candidates: tuple[tuple[str, float], ...] = (
        ("on_policy", 0.5),
        ("on_policy", 32.0),
        ("on_policy", 256.0),
        ("labeled", 0.1),
    )
    selection_conditions: int = 6  # pool conditions after the rollout and DAgger ones
    selection_duration_s: float = 3.0
    workers: int | None = None  # processes; None = one per CPU
    executor: str = DEFAULT_EXECUTOR  # models.executors.EXECUTORS: serial, local, ray

    @property
    def laws(self) -> tuple[str, ...]:
        return self.dataset.laws


def progress_callback(progress: Progress | None, label: str, total: int) -> Callable[[int], None]:
    """The advance(n) callback of a progress bar ``label`` of ``total`` steps (a no-op without one)."""
    return progress(label, total) if progress is not None else (lambda n: None)


def config_json(config: PipelineConfig) -> dict[str, Any]:
    """The config as plain JSON (what the label manifest and pipeline.json record)."""
    return json.loads(json.dumps(asdict(config), default=str))
