"""hil_runtime.conditions: the light reference evaluation and the conditions file format."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hil_runtime.conditions import (
    PAPER_CONDITIONS,
    Condition,
    ConditionError,
    load_conditions,
)

SIX = "[0, 0, 0, 0, 0, 0]"


def test_importing_it_pulls_in_no_science_package() -> None:
    code = (
        "import sys, hil_runtime.conditions as c; c.load_conditions(None)[0].reference(0.1); "
        "bad = [m for m in ('models', 'torch', 'pinocchio', 'pybullet', 'scipy') if m in sys.modules]; "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    done = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr


def test_paper_conditions_load_without_a_robot() -> None:
    conditions = load_conditions(None)
    assert PAPER_CONDITIONS.is_file()
    assert [c.name for c in conditions] == ["C1", "C2", "C3", "C4", "C5"]
    c1 = conditions[0]
    q, qd, qdd = c1.reference(np.array([0.0, 2.5]))
    assert q.shape == qd.shape == qdd.shape == (2, 6)
    assert q[0] == pytest.approx(np.zeros(6))  # f = 0.1 Hz, phase T/2: starts at 0
    assert q[1] == pytest.approx(0.5 * np.array(c1.amplitude_rad))
    assert c1.initial_position() == pytest.approx(np.zeros(6))


def test_check_limits_accepts_any_limits_object() -> None:
    class Limits:
        name = "configured"
        n_joints = 1
        position_lower_rad = np.array([-1.0])
        position_upper_rad = np.array([1.0])
        velocity_limit_rad_s = np.array([10.0])

    Condition("ok", (0.9,), (0.1,)).check_limits(Limits())
    with pytest.raises(ConditionError, match="reference position reaches 1.100 on joint 1"):
        Condition("far", (1.1,), (0.1,)).check_limits(Limits(), source="x.yaml")
    with pytest.raises(ConditionError, match="velocity"):
        Condition("fast", (0.9,), (5.0,)).check_limits(Limits())


def _condition(extra: str) -> str:
    return f"conditions:\n  - name: A\n    amplitude_rad: {SIX}\n{extra}"


BAD_FILES = [
    (_condition("    mismatch: {payload_kg: -1}\n"), "conditions[0].mismatch.payload_kg: must be >= 0"),
    (_condition("    mismatch: {inertia_scale: 0}\n"), "conditions[0].mismatch.inertia_scale[0]: must be > 0"),
    (_condition("    mismatch: {inertia_scale: [1, 1, -1, 1, 1, 1]}\n"), "mismatch.inertia_scale[2]: must be > 0"),
    (_condition("    mismatch: {mass_scale: -0.5}\n"), "mismatch.mass_scale[0]: must be > 0"),
    (_condition("    mismatch: {viscous_friction_nm_s: -0.1}\n"), "mismatch.viscous_friction_nm_s[0]: must be >= 0"),
    (_condition("    frequency_hz: -0.1\n"), "conditions[0].frequency_hz[0]: must be >= 0"),
    (_condition("    frequency_hz: [0.1, 0.1, -0.1, 0.1, 0.1, 0.1]\n"), "frequency_hz[2]: must be >= 0"),
    (_condition("    duration_s: 3\n    disturbance: {time_s: 4}\n"), "disturbance.time_s: 4 s is not before the end"),
    (_condition("    disturbance: {time_s: 1, torque_nm: [1, 2]}\n"), "disturbance.torque_nm: expected 6 values"),
    (_condition("    disturbance: {duration_s: -1}\n"), "disturbance.duration_s: must be >= 0"),
    (_condition("    duration_s: 0\n"), "duration_s: must be positive"),
    ("conditions:\n  - name: [1]\n    amplitude_rad: [0]\n", "conditions[0].name: expected a string"),
    ("", "empty file"),
    ("colour: red\nconditions:\n  - amplitude_rad: [0]\n", "unknown top-level field 'colour'"),
    (_condition("  - name: A\n    amplitude_rad: [0, 0, 0, 0, 0, 0]\n"), "duplicate name 'A'"),
    (_condition("    phase_s: .inf\n"), "phase_s: not finite"),
    (_condition("    amplitude_rad: '9' \n").replace(f"    amplitude_rad: {SIX}\n", ""), "expected a list of numbers"),
]


@pytest.mark.parametrize(("body", "message"), BAD_FILES)
def test_bad_values_are_one_line_errors_naming_file_and_field(tmp_path: Path, body: str, message: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(body)
    with pytest.raises(ConditionError) as info:
        load_conditions(path)
    text = str(info.value)
    assert message in text and "bad.yaml" in text and "\n" not in text
    assert info.value.exit_code == 2


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (bytes(range(256)) * 4, "not a UTF-8 text file"),
        (b"\x7fELF\x02\x01\x01\x00" + b"\x00" * 64, "not a text file"),
        (b"conditions:\n  - name: \x01\x02\n", "not valid YAML"),
    ],
)
def test_binary_files_are_refused(tmp_path: Path, data: bytes, message: str) -> None:
    path = tmp_path / "bin.yaml"
    path.write_bytes(data)
    with pytest.raises(ConditionError, match=message) as info:
        load_conditions(path)
    assert "bin.yaml" in str(info.value)


def test_a_directory_and_a_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConditionError, match="not a regular file"):
        load_conditions(tmp_path)
    with pytest.raises(ConditionError, match="file not found"):
        load_conditions(tmp_path / "nope.yaml")


def test_zero_frequency_and_pi_expressions_are_accepted(tmp_path: Path) -> None:
    path = tmp_path / "ok.yaml"
    path.write_text(
        "conditions:\n  - name: Z\n    amplitude_rad: [pi/4, -2*pi/3]\n    frequency_hz: 0\n    disturbance: null\n"
    )
    (c,) = load_conditions(path)
    assert c.amplitude_rad == pytest.approx((math.pi / 4, -2 * math.pi / 3))
    assert c.disturbance is None
    q, qd, _ = c.reference(1.0)
    assert np.all(np.isfinite(q)) and qd == pytest.approx(np.zeros(2))


class _Limits:
    name = "configured"
    n_joints = 1
    position_lower_rad = np.array([-2.5])
    position_upper_rad = np.array([2.5])
    velocity_limit_rad_s = np.array([10.0])


def test_a_peak_between_the_old_samples_is_refused() -> None:
    # 2 Hz over 1000 s: 2001 samples land every 0.5 s, at the same phase, where sin is 0 (q = 2.4)
    peak = Condition("peak", (0.2,), (2.0,), duration_s=1000.0, shape="sine", phase_s=0.0, offset_rad=(2.4,))
    assert peak.reference(np.linspace(0.0, 1000.0, 2001))[0].max() < 2.5  # the samples stay inside
    with pytest.raises(ConditionError, match="reference position reaches 2.600 on joint 1"):
        peak.check_limits(_Limits())


def test_a_reference_whose_every_sample_is_at_rest_is_refused() -> None:
    # 400 Hz: period 2.5 ms = the old sample spacing over 5 s; phase puts every sample on a crest (qd = 0)
    fast = Condition("fast", (0.1,), (400.0,), duration_s=5.0, shape="sine", phase_s=-1.0 / 1600.0)
    assert np.abs(fast.reference(np.linspace(0.0, 5.0, 2001))[1]).max() < 1e-6
    with pytest.raises(ConditionError, match="reference velocity reaches 251.327 on joint 1"):
        fast.check_limits(_Limits())


@pytest.mark.parametrize("seed", range(20))
def test_the_extrema_are_the_shapes_exact_ones(seed: int) -> None:
    rng = np.random.default_rng(seed)
    shape = ("raised_sine", "sine", "constant")[seed % 3]
    duration = float(rng.uniform(0.1, 3.0))
    c = Condition(
        "r",
        tuple(rng.uniform(-2, 2, 3)),
        tuple(rng.uniform(0, 2, 3)),
        duration_s=duration,
        shape=shape,
        phase_s=float(rng.uniform(-3, 3)),
        offset_rad=tuple(rng.uniform(-1, 1, 3)),
    )
    q, qd, _ = c.reference(np.linspace(0.0, duration, 400_001))
    lowest, highest, fastest = c.extrema()
    # never below what any sample reaches, and a dense sampling reaches them within its spacing
    assert np.all(lowest <= q.min(axis=0) + 1e-12) and np.all(highest >= q.max(axis=0) - 1e-12)
    assert np.all(fastest >= np.abs(qd).max(axis=0) - 1e-12)
    np.testing.assert_allclose([lowest, highest, fastest], [q.min(0), q.max(0), np.abs(qd).max(0)], atol=1e-6)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ("    duration_s: 1.0e8\n", "duration_s: 1e+08 s is above the limit 3600 s"),
        ("    frequency_hz: 1.0e4\n", "frequency_hz[0]: must be <= 1000"),
        ("    phase_s: 1.0e300\n", "phase_s: |1e+300| s is above the limit"),
        ("    disturbance: {time_s: 1, duration_s: 1.0e300}\n", "disturbance.duration_s: must be <= 5"),
    ],
)
def test_huge_durations_frequencies_and_phases_are_refused(tmp_path: Path, extra: str, message: str) -> None:
    path = tmp_path / "huge.yaml"
    path.write_text(_condition(extra))
    with pytest.raises(ConditionError) as info:
        load_conditions(path)
    assert message in str(info.value) and "huge.yaml" in str(info.value)


def test_an_hour_long_condition_is_accepted(tmp_path: Path) -> None:
    path = tmp_path / "long.yaml"
    path.write_text(_condition("    duration_s: 3600\n"))
    (c,) = load_conditions(path)
    assert c.duration_s == 3600.0
