"""The LMPC's velocity input filter (hil_runtime.velocity_filter): the recurrence, its noise gain, its
bad inputs, and where the runtime applies it (lmpc mode only, reset on activation)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from hil_runtime.bundle import PolicyBundle
from hil_runtime.config import RuntimeConfigError, load_runtime_config
from hil_runtime.controller import Controller
from hil_runtime.velocity_filter import VelocityFilter, filter_pole, step_noise_gain
from sim_target.testing.ur5 import PD_BUNDLE
from tests.unit.hil_runtime.support import config_dict


def test_the_recurrence_and_its_first_sample() -> None:
    f = VelocityFilter(50.0, 1e-3, 2)
    f.reset()
    a = math.exp(-2 * math.pi * 50 * 1e-3)
    assert np.array_equal(f.filter(np.array([1.0, -2.0])), [1.0, -2.0])  # the first sample passes
    out = f.filter(np.array([3.0, 0.0]))
    assert np.allclose(out, [a * 1 + (1 - a) * 3, a * -2 + (1 - a) * 0])
    assert f.filter(np.array([0.0, 0.0])) is out  # one buffer, no allocation per call
    f.reset()
    assert np.array_equal(f.filter(np.array([5.0, 5.0])), [5.0, 5.0])  # reset forgets


def test_a_non_finite_sample_is_passed_on_and_not_kept() -> None:
    f = VelocityFilter(50.0, 1e-3, 2)
    f.reset()
    f.filter(np.array([1.0, 1.0]))
    bad = f.filter(np.array([np.nan, 1.0]))
    assert np.isnan(bad[0])  # the supervisor sees it
    assert np.allclose(f.filter(np.array([1.0, 1.0])), [1.0, 1.0])  # the state stayed finite


def test_the_noise_gain_is_the_measured_one() -> None:
    """(1 - a) sqrt(2 / (1 + a)): the RMS cycle-to-cycle change of the output per unit of white input noise."""
    rng = np.random.default_rng(4)
    for cutoff in (20.0, 50.0, 200.0):
        f = VelocityFilter(cutoff, 1e-3, 1)
        f.reset()
        out = np.array([f.filter(x).copy() for x in rng.normal(size=(60_000, 1))])[1000:, 0]
        measured = float(np.std(np.diff(out)))
        assert measured == pytest.approx(step_noise_gain(f.pole), rel=0.03), cutoff
    assert step_noise_gain(0.0) == pytest.approx(math.sqrt(2.0))


@pytest.mark.parametrize("cutoff", [0.0, -5.0, 500.0, 1e4, math.nan, math.inf])
def test_a_cutoff_outside_zero_to_nyquist_is_refused(cutoff: float) -> None:
    with pytest.raises(ValueError, match="Nyquist"):
        filter_pole(cutoff, 1e-3)


def test_the_runtime_filters_the_lmpc_input_only(tmp_path: Path) -> None:
    bundle = PolicyBundle.load(PD_BUNDLE)
    q = np.full(6, 0.1)
    lmpc, fb = Controller(bundle, "lmpc", velocity_filter_hz=50.0), Controller(bundle, "fb", velocity_filter_hz=50.0)
    assert lmpc.velocity_filter is not None and fb.velocity_filter is None
    lmpc.reset(np.zeros(6))
    lmpc.step(q, np.zeros(6), q, np.zeros(6), np.zeros(6))  # primes the filter at rest
    lmpc.commit(np.zeros(6))
    tau_filtered = lmpc.step(q, np.ones(6), q, np.zeros(6), np.zeros(6))[0].copy()
    raw = Controller(bundle, "lmpc")
    raw.reset(np.zeros(6))
    tau_raw = raw.step(q, np.ones(6), q, np.zeros(6), np.zeros(6))[0].copy()
    assert lmpc.velocity_filter is not None
    a = lmpc.velocity_filter.pole
    reference = Controller(bundle, "lmpc")
    reference.reset(np.zeros(6))
    tau_expected = reference.step(q, np.full(6, 1.0 - a), q, np.zeros(6), np.zeros(6))[0]
    assert np.allclose(tau_filtered, tau_expected) and not np.allclose(tau_filtered, tau_raw)
    path = tmp_path / "rt.yaml"
    path.write_text(yaml.safe_dump(config_dict(bundle={"path": str(PD_BUNDLE), "velocity_filter_hz": 500.0})))
    nyquist = r"bundle.velocity_filter_hz: velocity filter: cutoff 500.0 Hz must be above 0 and below the Nyquist"
    with pytest.raises(RuntimeConfigError, match=nyquist):
        load_runtime_config(path)
