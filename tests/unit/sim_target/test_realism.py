"""The realism model (sim_target/realism.py) against closed forms, and its profiles' validation."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sim_target.realism import (
    RealismError,
    RealismModel,
    RealismSpec,
    encoder_step_rad,
    friction_nm,
    lag_period,
    quantize,
)
from sim_target.realism_profiles import PROFILE_NAMES, RealismProfile, bind_profile, load_realism, parse_profile

PERIOD_S = 1e-3
LIMIT_NM = np.array([102.0, 102.0, 66.0, 34.0, 34.0, 34.0])


def spec(**sections: Any) -> RealismSpec:
    return bind_profile(parse_profile(sections, "test"), "test", 6, PERIOD_S, PERIOD_S / 32, LIMIT_NM)


def test_quantization_error_is_within_half_an_encoder_step() -> None:
    counts = 1 << 16
    step = encoder_step_rad(np.full(6, counts))
    assert step[0] == pytest.approx(2 * math.pi / counts)  # 9.6e-5 rad for 16 bits
    model = RealismModel(spec(sensing={"encoder_counts_per_rev": counts}))
    q = np.random.default_rng(1).uniform(-3, 3, (1000, 6))
    model.reset(q[0], np.zeros(6))
    q_meas, _ = model.sense(q, np.zeros_like(q))
    error = q_meas - q
    assert np.all(np.abs(error) <= step / 2 + 1e-15)
    assert np.allclose(np.round(q_meas / step), q_meas / step)  # whole increments
    assert np.std(error) == pytest.approx(step[0] / math.sqrt(12), rel=0.1)  # uniform over one step


def test_finite_difference_velocity_noise_variance_is_two_sigma_squared_over_period_squared() -> None:
    sigma = 1e-4
    model = RealismModel(spec(sensing={"encoder_noise_rad": sigma, "velocity": "difference"}))
    q = np.zeros(6)
    model.reset(q, q)
    samples = np.array([model.sense(q, q)[1] for _ in range(20000)])[1:]
    expected = 2 * sigma**2 / PERIOD_S**2  # var(n_k - n_{k-1}) / T^2
    assert np.var(samples) == pytest.approx(expected, rel=0.05)
    # successive differences share one noise sample: lag-1 correlation -1/2
    corr = np.corrcoef(samples[1:, 0], samples[:-1, 0])[0, 1]
    assert corr == pytest.approx(-0.5, abs=0.03)


def test_velocity_of_a_ramp_is_exact_by_differencing_and_delayed_by_whole_periods() -> None:
    model = RealismModel(spec(sensing={"velocity": "difference", "delay_periods": 2}))
    v = np.full(6, 0.3)
    model.reset(np.zeros(6), v)
    readings = [model.sense(v * k * PERIOD_S, v) for k in range(6)]
    for k, (q_meas, qd_meas) in enumerate(readings):
        np.testing.assert_allclose(q_meas, v * max(k - 2, 0) * PERIOD_S, atol=1e-15)
        np.testing.assert_allclose(qd_meas, v, rtol=1e-9)


def test_velocity_filter_is_a_first_order_low_pass() -> None:
    cutoff = 50.0
    model = RealismModel(spec(sensing={"velocity_filter_cutoff_hz": cutoff}))
    model.reset(np.zeros(6), np.zeros(6))
    model.sense(np.zeros(6), np.zeros(6))
    alpha = 1 - math.exp(-2 * math.pi * cutoff * PERIOD_S)
    out = [model.sense(np.zeros(6), np.ones(6))[1][0] for _ in range(10)]
    np.testing.assert_allclose(out, 1 - (1 - alpha) ** np.arange(1, 11), rtol=1e-12)


def test_torque_lag_step_response_matches_the_continuous_first_order_lag() -> None:
    bandwidth = 200.0
    model = RealismModel(spec(actuation={"torque_bandwidth_hz": bandwidth}))
    model.reset(np.zeros(6), np.zeros(6))
    w = 2 * math.pi * bandwidth
    held = [model.actuate(np.full(6, 10.0), np.zeros(6))[0] for _ in range(5)]
    for k, mean in enumerate(held):
        # the exact mean of 10 (1 - exp(-w t)) over [kT, (k+1)T]
        exact = 10 * (1 - (math.exp(-w * k * PERIOD_S) - math.exp(-w * (k + 1) * PERIOD_S)) / (w * PERIOD_S))
        assert mean == pytest.approx(exact, rel=1e-12)
    mean, end = lag_period(np.zeros(1), np.ones(1), 0.0, PERIOD_S)  # no bandwidth: ideal
    assert mean[0] == end[0] == 1.0


def test_torque_quantum_is_one_per_mille_of_the_rated_torque_and_dead_band_zeroes_small_commands() -> None:
    model = RealismModel(spec(actuation={"rated_torque_ratio_of_limit": 0.5, "torque_dead_band_nm": 0.2}))
    model.reset(np.zeros(6), np.zeros(6))
    out = model.actuate(np.array([1.234, 0.19, -0.21, 5.0, 0.0, 1.0]), np.zeros(6))
    quantum = LIMIT_NM * 0.5 / 1000
    np.testing.assert_allclose(out, quantize(np.array([1.234, 0.0, -0.21, 5.0, 0.0, 1.0]), quantum))
    assert out[0] == pytest.approx(round(1.234 / 0.051) * 0.051)
    assert out[1] == 0.0


def test_ripple_follows_the_joint_position() -> None:
    model = RealismModel(spec(actuation={"torque_ripple_ratio": 0.02, "torque_ripple_cycles_per_rev": 200}))
    model.reset(np.zeros(6), np.zeros(6))
    q = np.full(6, 0.01)
    np.testing.assert_allclose(model.actuate(np.full(6, 10.0), q), 10 * (1 + 0.02 * math.sin(200 * 0.01)))


def test_friction_torque_closed_form_and_never_reversing_the_joint() -> None:
    world = spec(
        plant={
            "viscous_friction_nm_s_per_rad": 0.5,
            "coulomb_friction_nm": 2.0,
            "stribeck_friction_nm": 1.0,
            "stribeck_velocity_rad_s": 0.1,
            "friction_smoothing_velocity_rad_s": 1e-3,
        }
    )
    qd = np.array([-1.0, -0.1, 0.05, 0.1, 0.5, 2.0])
    expected = 0.5 * qd + (2.0 + 1.0 * np.exp(-((qd / 0.1) ** 2))) * np.tanh(qd / 1e-3)
    np.testing.assert_allclose(friction_nm(qd, world.plant), expected)
    model = RealismModel(world)
    big = np.full(6, 10.0)  # kg m^2: friction far below the stopping torque
    np.testing.assert_allclose(model.friction_nm(qd, big), expected)
    tiny = np.full(6, 1e-4)  # a light wrist: friction capped at the torque that stops it in a period
    np.testing.assert_allclose(model.friction_nm(qd, tiny), np.sign(qd) * 1e-4 * np.abs(qd) / PERIOD_S)


def test_same_seed_same_noise_and_reset_restarts_it() -> None:
    world = spec(sensing={"encoder_noise_rad": 1e-4}, seed=7)
    a, b = RealismModel(world), RealismModel(world)
    q = np.zeros(6)
    a.reset(q, q)
    b.reset(q, q)
    first = [a.sense(q, q)[0] for _ in range(3)]
    np.testing.assert_array_equal(first, [b.sense(q, q)[0] for _ in range(3)])
    a.reset(q, q)
    np.testing.assert_array_equal(first, [a.sense(q, q)[0] for _ in range(3)])
    c = RealismModel(spec(sensing={"encoder_noise_rad": 1e-4}, seed=8))
    c.reset(q, q)
    assert not np.array_equal(first[0], c.sense(q, q)[0])


def test_shipped_profiles_load_and_ideal_is_ideal() -> None:
    for name in PROFILE_NAMES:
        world = load_realism(name, 6, PERIOD_S, PERIOD_S / 2, LIMIT_NM)
        assert world.is_ideal == (name == "ideal")
    assert RealismModel(load_realism("ideal", 6, PERIOD_S, PERIOD_S, LIMIT_NM)).is_ideal
    assert bind_profile(RealismProfile(), "x", 7, PERIOD_S, PERIOD_S, np.ones(7)).is_ideal


BAD_PROFILES = [
    ("sensing: {encoder_noise_rad: -1.0e-5}\n", "sensing.encoder_noise_rad"),
    ("sensing: {encoder_noise_rad: .nan}\n", "sensing.encoder_noise_rad"),
    ("actuation: {torque_bandwidth_hz: .inf}\n", "actuation.torque_bandwidth_hz"),
    ("actuation: {torque_bandwidth_hz: 20000}\n", "actuation.torque_bandwidth_hz"),  # Nyquist of 31 us: 16 kHz
    ("sensing: {velocity_filter_cutoff_hz: 600}\n", "sensing.velocity_filter_cutoff_hz"),  # Nyquist of 1 ms
    ("sensing: {encoder_noise_radians: 1.0e-5}\n", "sensing.encoder_noise_radians"),  # unknown field
    ("plant: {coulomb_friction_nm: [1, 2, 3]}\n", "plant.coulomb_friction_nm"),  # wrong length
    ("plant: {payload_kg: -0.5}\n", "plant.payload_kg"),
    ("colour: blue\n", "colour"),
    ("- 1\n- 2\n", "expected a mapping"),
]


@pytest.mark.parametrize(("text", "field"), BAD_PROFILES)
def test_bad_profiles_are_refused_with_one_line_naming_file_and_field(tmp_path: Path, text: str, field: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(RealismError) as info:
        load_realism(path, 6, PERIOD_S, PERIOD_S / 32, LIMIT_NM)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message and field in message
    assert info.value.exit_code == 2


def test_unknown_profile_name_is_refused() -> None:
    with pytest.raises(RealismError, match="neither a profile"):
        load_realism("realistc", 6, PERIOD_S, PERIOD_S, LIMIT_NM)
