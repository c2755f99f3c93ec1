"""ONNX export of a law's step graph: the same ``law.step`` definition, traced with torch.

Graph inputs (float64, leading dynamic batch axis "batch"): q, qd, q_d, qd_d, qdd_d (B, N) and
state (B, S); outputs tau_fb (B, N) and next_state (B, S). A stateless law (PD, SMC) still has a
state input and output of width S = 1 (a zero that passes through): some runtimes reject
zero-width tensors, and a fixed layout keeps the runtime's loop the same for every law.
``onnx_state_width(law)`` gives S. float64 keeps the graph within 1e-6 of the numpy law.

torch 2.13 defaults to the dynamo exporter, which needs onnxscript (not installed); the
TorchScript exporter (dynamo=False) handles these graphs and is used here.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np

from models.feedback.base import FeedbackLaw

INPUT_NAMES = ["q", "qd", "q_d", "qd_d", "qdd_d", "state"]
OUTPUT_NAMES = ["tau_fb", "next_state"]
OPSET = 17


def onnx_state_width(law: FeedbackLaw) -> int:
    """Width of the graph's state input/output: the law's state size, or 1 for a stateless law."""
    return max(law.state_size, 1)


def run_step_numpy(law: FeedbackLaw, state: np.ndarray, *signals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The numpy law on the ONNX state layout (drops/keeps the placeholder column of a stateless law)."""
    tau, next_state = law.step(np, state[:, : law.state_size], *signals)
    return tau, (state if law.state_size == 0 else next_state)


def export_law_onnx(law: FeedbackLaw, path: str | Path) -> Path:
    """Write the law's step graph to ``path`` (ONNX, opset 17, dynamic batch) and return the path."""
    import torch

    class Step(torch.nn.Module):
        def forward(self, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any, state: Any) -> Any:  # torch tensors
            # The tracer drops inputs a law does not read (PD ignores qdd_d); a zero-weighted use keeps
            # every input in the graph so all six laws share one signature.
            anchor = 0.0 * (q + qd + q_d + qd_d + qdd_d)
            if law.state_size == 0:
                tau, _ = law.step(torch, state[:, :0], q, qd, q_d, qd_d, qdd_d)
                return tau + anchor, state + 0.0  # an explicit op so the output is not the input itself
            tau, next_state = law.step(torch, state, q, qd, q_d, qd_d, qdd_d)
            return tau + anchor, next_state

    n, batch = law.n_joints, 2
    example = tuple(torch.zeros(batch, n, dtype=torch.float64) for _ in range(5))
    example += (torch.as_tensor(law.initial_state(np.zeros((batch, n))), dtype=torch.float64),)
    if law.state_size == 0:
        example = example[:5] + (torch.zeros(batch, 1, dtype=torch.float64),)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    axes = {name: {0: "batch"} for name in INPUT_NAMES + OUTPUT_NAMES}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TorchScript exporter deprecation and tracer notices
        torch.onnx.export(
            Step(),
            example,
            str(path),
            input_names=INPUT_NAMES,
            output_names=OUTPUT_NAMES,
            dynamic_axes=axes,
            opset_version=OPSET,
            dynamo=False,
        )
    return path
