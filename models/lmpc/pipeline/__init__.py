"""The LMPC pipeline: D_input -> Theorem 2 sampling -> HMPC labels -> emulators -> policy bundles.

Stages (each reads the previous stage's file, so any can be rerun alone), one module each:

    dataset   <work>/raw.h5        D_input (models.lmpc.dataset)                      labeling.py
    label     <work>/labels.h5     per law: optimal, uniform and test indices into     labeling.py
                                   raw.h5, HMPC labels
    train     <work>/training.json optimal vs uniform, 3 seeds each;                  training.py
                                   <work>/sampling_curves.png
    augment   <work>/augmented.pkl beyond the paper: residual target, on-policy data,  augment.py
                                   trust region (docs/lmpc.md)
    export    <bundles>/<robot>/<law>/{policy.onnx, manifest.json}                     export.py

``config.py`` holds the settings every stage reads, ``run.py`` runs the stages in order on one
executor (``models.executors``); the command line is ``hil pipeline`` (models/cli/pipeline.py).

Splits: the conditions are split into a sampling pool (the first ``pool_conditions``) and held-out
conditions from which a fixed uniform test set is drawn; the samplers only see the pool. The budget
(100,000, the paper's) is shared equally by the six laws; each law gets its own emulator.
"""

from models.lmpc.pipeline.augment import select_margins, stage_augment, theorem2_repeats
from models.lmpc.pipeline.config import PipelineConfig, Progress, config_json
from models.lmpc.pipeline.export import export_deployed, stage_export
from models.lmpc.pipeline.labeling import (
    LABELS_SCHEMA,
    LawLabels,
    choose_samples,
    load_labels,
    stage_dataset,
    stage_label,
)
from models.lmpc.pipeline.run import run_pipeline
from models.lmpc.pipeline.training import plot_sampling_curves, stage_train, summarize_training

__all__ = [
    "LABELS_SCHEMA",
    "LawLabels",
    "PipelineConfig",
    "Progress",
    "choose_samples",
    "config_json",
    "export_deployed",
    "load_labels",
    "plot_sampling_curves",
    "run_pipeline",
    "select_margins",
    "stage_augment",
    "stage_dataset",
    "stage_export",
    "stage_label",
    "stage_train",
    "summarize_training",
    "theorem2_repeats",
]
