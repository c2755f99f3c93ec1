"""The fault campaign's crafted bundles (models/lab/faults/crafted.py): the runtime's own loader
accepts them (sha256, layout, probes, saturation), they misbehave only inside their trigger band,
and a tampered copy is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hil_runtime.bundle import BundleError, NonFiniteOutputError, PolicyBundle
from models.lab.faults.crafted import (
    SATURATING_TORQUE_NM,
    TRIGGER_HALF_WIDTH_RAD,
    CraftKind,
    craft_bundle,
    tamper_bundle,
)

ROOT = Path(__file__).resolve().parents[4]
PD = ROOT / "models" / "bundles" / "ur5_paper" / "pd"
Q = np.array([0.0, -0.5, 0.8, -0.3, 0.0, 0.0])
Z = np.zeros(6)


def _step(bundle: PolicyBundle, q0: float) -> np.ndarray:
    q = Q.copy()
    q[0] = q0
    return np.array(bundle.step(q, Z, q + 0.01, Z, Z, np.zeros(bundle.state_size))[0])


@pytest.mark.parametrize("kind", ["nan", "inf", "nan_both", "saturate"])
def test_crafted_bundles_load_and_misbehave_only_in_their_band(tmp_path: Path, kind: CraftKind) -> None:
    trigger = craft_bundle(PD, tmp_path / kind, kind)
    crafted, original = PolicyBundle.load(tmp_path / kind), PolicyBundle.load(PD)
    outside = trigger + 3 * TRIGGER_HALF_WIDTH_RAD
    np.testing.assert_array_equal(_step(crafted, outside), _step(original, outside))
    if kind == "nan_both":
        with pytest.raises(NonFiniteOutputError):
            _step(crafted, trigger)
        return
    inside = _step(crafted, trigger)
    if kind == "saturate":
        np.testing.assert_array_equal(inside, np.full(6, SATURATING_TORQUE_NM))
    else:  # the graph's tau is non-finite: the bundle gives the law's torque and counts it
        assert np.isfinite(inside).all() and crafted.nonfinite_fallbacks == 1
    assert (PD / "policy.onnx").read_bytes() != (tmp_path / kind / "policy.onnx").read_bytes()


def test_a_tampered_copy_is_refused_by_sha256(tmp_path: Path) -> None:
    tamper_bundle(PD, tmp_path / "t")
    with pytest.raises(BundleError, match="sha256 mismatch"):
        PolicyBundle.load(tmp_path / "t")
