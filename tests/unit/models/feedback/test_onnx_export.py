"""Each law's ONNX step graph (onnxruntime) matches the numpy law to 1e-6 on random inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from models.feedback import LAW_NAMES, make_law
from models.feedback.export import INPUT_NAMES, OPSET, export_law_onnx, onnx_state_width, run_step_numpy
from models.robots import load_robot

ROBOT = load_robot("ur5_paper")


@pytest.mark.parametrize("name", LAW_NAMES)
def test_onnx_step_matches_numpy(name: str, tmp_path: Path) -> None:
    law = make_law(name, ROBOT)
    path = export_law_onnx(law, tmp_path / f"{name}.onnx")
    model = onnx.load(str(path))
    assert [i.name for i in model.graph.input] == INPUT_NAMES
    assert max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx")) >= OPSET
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(3)
    for batch in (1, 7):  # the batch axis is dynamic
        signals = [rng.normal(size=(batch, 6)) for _ in range(5)]
        width = onnx_state_width(law)
        state = rng.normal(size=(batch, width))
        if law.state_size:
            state = law.initial_state(signals[0]) + 0.05 * state
        for _ in range(3):  # a few steps, feeding the state back
            tau_ort, next_ort = session.run(None, dict(zip(INPUT_NAMES, [*signals, state], strict=True)))
            tau_np, next_np = run_step_numpy(law, state, *signals)
            np.testing.assert_allclose(tau_ort, tau_np, rtol=0, atol=1e-6)
            np.testing.assert_allclose(next_ort, next_np, rtol=0, atol=1e-6)
            assert next_ort.shape == (batch, width)
            state = next_ort
            signals = [s + 0.01 * rng.normal(size=s.shape) for s in signals]
