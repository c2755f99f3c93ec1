"""Effort metrics, the deployable verdict and the effort-aware composite (models/effort.py)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from models.effort import (
    EFFORT_WEIGHTS,
    TRACKING_SHARE,
    deployable,
    effort_composite,
    effort_metrics,
    format_effort_table,
    max_torque_step_nm,
)
from models.scoring import WEIGHTS

T_S = 1e-3
LIMIT = np.array([100.0, 50.0])
RATE = 1000.0 * LIMIT / 87.0  # the "scaled" rule (hil_runtime.rate_limit): 1.149 N·m per ms on joint 1


def _signal(freq_hz: float, amplitude: float, n: int = 2000) -> np.ndarray:
    t = np.arange(n) * T_S
    return amplitude * np.sin(2 * math.pi * freq_hz * t)


def test_metrics_of_sinusoids_match_closed_forms() -> None:
    n = 2000
    slow, fast = _signal(5.0, 10.0, n), _signal(200.0, 1.0, n)
    tau = np.stack([slow, fast], axis=1)
    qd = np.ones_like(tau)
    e = effort_metrics(tau, qd, LIMIT, T_S)
    assert e["torque_rms_nm"] == pytest.approx([10 / math.sqrt(2), 1 / math.sqrt(2)], rel=1e-3)
    # high-frequency part: none of the 5 Hz wave, all of the 200 Hz one
    assert e["torque_hf_rms_nm"][0] < 1e-9
    assert e["torque_hf_rms_nm"][1] == pytest.approx(1 / math.sqrt(2), rel=1e-3)
    # chatter of A sin(w t): RMS of A (sin(w(t+T)) - sin(w t)) = A * 2 sin(w T / 2) / sqrt 2
    for j, (f, a) in enumerate(((5.0, 10.0), (200.0, 1.0))):
        assert e["chatter_nm"][j] == pytest.approx(a * 2 * math.sin(math.pi * f * T_S) / math.sqrt(2), rel=1e-2)
    assert e["energy_j"] == pytest.approx(list(np.abs(tau).sum(axis=0) * T_S))
    # 200 Hz sampled at 1 kHz peaks at sin(72 deg) = 0.951 of its amplitude
    assert e["peak_torque_ratio"] == pytest.approx([10 / 100, math.sin(math.radians(72)) / 50], rel=1e-3)


def test_rows_cut_a_faulted_run() -> None:
    tau = np.zeros((100, 2))
    tau[50:] = 80.0  # padding after a fault must not count
    e = effort_metrics(tau, np.zeros_like(tau), LIMIT, T_S, rows=50)
    assert e["chatter_nm"] == [0.0, 0.0]


def test_torque_step_limit_is_the_rate_times_the_period() -> None:
    np.testing.assert_allclose(max_torque_step_nm(np.array([1000.0, 2000.0]), 1e-3), [1.0, 2.0])


def _run(chatter: list[float], step: list[float], peak: tuple[float, ...] = (0.5, 0.5), **extra: Any) -> dict[str, Any]:
    return {
        "finite": True,
        "within_limits": True,
        "effort": {"chatter_nm": list(chatter), "max_torque_step_nm": list(step), "peak_torque_ratio": list(peak)},
        **extra,
    }


def test_deployable_rules() -> None:
    ok = _run([0.1, 0.1], [0.5, 0.2])
    assert deployable(ok, None, LIMIT, T_S, RATE)["deployable"]
    # chatter above 2 % of the limit (2 N·m on joint 1) without an FB reference: refused
    loud = _run([3.0, 0.1], [0.5, 0.2])
    verdict = deployable(loud, None, LIMIT, T_S, RATE)
    assert not verdict["deployable"] and "chatter" in verdict["reasons"][0]
    # ... but allowed when the FB law chatters 2 N·m on the same run (2 x 2 = 4 N·m allowed)
    assert deployable(loud, _run([2.0, 0.1], [0.5, 0.2]), LIMIT, T_S, RATE)["deployable"]
    # the torque rate: 100 N·m limit -> 1.149 N·m per 1 ms cycle
    fast = _run([0.1, 0.1], [1.2, 0.2])
    assert "torque rate" in deployable(fast, None, LIMIT, T_S, RATE)["reasons"][0]
    assert deployable(_run([0.1, 0.1], [1.14, 0.2]), None, LIMIT, T_S, RATE)["deployable"]
    # a limit trip and a command at the torque limit
    assert "limit trip" in deployable({**ok, "within_limits": False}, None, LIMIT, T_S, RATE)["reasons"][0]
    assert not deployable({**ok, "hil": {"fault": "velocity_limit: x"}}, None, LIMIT, T_S, RATE)["deployable"]
    assert not deployable(_run([0.1, 0.1], [0.5, 0.2], peak=(1.0, 0.2)), None, LIMIT, T_S, RATE)["deployable"]


def test_effort_composite_weights_and_ranking() -> None:
    assert TRACKING_SHARE * sum(WEIGHTS) + sum(EFFORT_WEIGHTS) == pytest.approx(1.0)
    tracking = {"rmse": 1.0, "mae": 1.0, "p95": 1.0, "peak": 1.0, "settle_s": 1.0, "dedt_rms": 1.0}
    better = {k: 0.1 for k in tracking}
    calm = {"torque_rms_ratio": 0.1, "chatter_ratio": 0.001, "torque_hf_ratio": 0.001, "energy_total_j": 1.0}
    loud = {"torque_rms_ratio": 0.3, "chatter_ratio": 0.3, "torque_hf_ratio": 0.3, "energy_total_j": 10.0}
    metrics = {("fb", "C"): tracking, ("x", "C"): better}
    effort = {("fb", "C"): calm, ("x", "C"): loud}
    scores = effort_composite(metrics, effort)
    assert scores["x"] > scores["fb"]  # tracks 10x better, but chatters: worse on the effort-aware score
    assert scores["x"] == pytest.approx(TRACKING_SHARE * 0.1 * sum(WEIGHTS) + sum(EFFORT_WEIGHTS))


def test_table_flags_and_leaves_non_deployable_out_of_the_average() -> None:
    results = {
        "config": {"modes": ["fb", "lmpc"], "realism": "realistic"},
        "conditions": [{"name": "C1"}],
        "table": {
            "pd": {
                "fb": {"not_deployable_conditions": []},
                "lmpc": {"eta": 0.5, "eta_effort": 0.2, "not_deployable_conditions": []},
            },
            "smc": {
                "fb": {"not_deployable_conditions": []},
                "lmpc": {"eta": 0.9, "eta_effort": -3.0, "not_deployable_conditions": ["C1"]},
            },
        },
    }
    text = "\n".join(format_effort_table(results))
    assert "| smc | 1/1 | 90.0 | -300.0 | 0/1 ✗ |" in text
    assert "η_LMPC 50.0 %" in text and "(1 laws)" in text
    assert "Left out of the LMPC average (not deployable): smc." in text
