"""The fault campaign's crafted bundles (models/lab/faults/crafted.py): the runtime's own loader
accepts them (sha256, layout, probes, saturation), they misbehave only inside their trigger band,
and a tampered copy is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hil_runtime.bundle import BundleError, PolicyBundle
from hil_runtime.supervisor import policy_torque
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


def _outputs(bundle: PolicyBundle, q0: float) -> tuple[np.ndarray, ...]:
    q = Q.copy()
    q[0] = q0
    return tuple(np.array(a) for a in bundle.step(q, Z, q + 0.01, Z, Z, np.zeros(bundle.state_size)))


def _step(bundle: PolicyBundle, q0: float) -> np.ndarray:
    """The torque the runtime would command: the bundle's output through the supervisor's rule."""
    usable = policy_torque(*_outputs(bundle, q0))
    assert usable is not None, "nothing finite to command"
    return usable[0]


@pytest.mark.parametrize("kind", ["nan", "inf", "nan_both", "saturate"])
def test_crafted_bundles_load_and_misbehave_only_in_their_band(tmp_path: Path, kind: CraftKind) -> None:
    trigger = craft_bundle(PD, tmp_path / kind, kind)
    crafted, original = PolicyBundle.load(tmp_path / kind), PolicyBundle.load(PD)
    outside = trigger + 3 * TRIGGER_HALF_WIDTH_RAD
    np.testing.assert_array_equal(_step(crafted, outside), _step(original, outside))
    if kind == "nan_both":  # nothing finite to command: the supervisor's FAULT policy_nonfinite
        assert policy_torque(*_outputs(crafted, trigger)) is None
        return
    inside = _step(crafted, trigger)
    if kind == "saturate":
        np.testing.assert_array_equal(inside, np.full(6, SATURATING_TORQUE_NM))
    else:  # the graph's tau is non-finite: the supervisor's rule gives the law's torque
        tau, tau_fb, _ = _outputs(crafted, trigger)
        assert not np.isfinite(tau).all() and np.isfinite(inside).all() and np.array_equal(inside, tau_fb)
    assert (PD / "policy.onnx").read_bytes() != (tmp_path / kind / "policy.onnx").read_bytes()


def test_a_tampered_copy_is_refused_by_sha256(tmp_path: Path) -> None:
    tamper_bundle(PD, tmp_path / "t")
    with pytest.raises(BundleError, match="sha256 mismatch"):
        PolicyBundle.load(tmp_path / "t")
