from __future__ import annotations

import numpy as np
import pytest

from models.scoring import WEIGHTS, composite_scores, improvement, run_metrics


def test_metrics_of_a_known_error_signal() -> None:
    t = np.arange(5000) * 1e-3
    q_ref = np.zeros((5000, 2))
    q = np.zeros((5000, 2))
    q[:, 0] = np.radians(4.0)  # 4 deg on joint 1 until t = 2.5 s, then 0: joint mean 2 deg
    q[2500:, 0] = 0.0
    m = run_metrics(t, q, q_ref, disturbance_time_s=2.0)
    assert m["mae"] == pytest.approx(1.0)  # 4 deg on half the samples of one of two joints
    assert m["rmse"] == pytest.approx(2.0)
    assert m["peak"] == pytest.approx(4.0)
    assert m["settle_s"] == pytest.approx(0.5)  # joint mean 2 deg > 1 deg until 2.5 s
    assert m["dedt_rms"] == pytest.approx(np.sqrt((4.0 / 1e-3) ** 2 / (4999 * 2)))


def test_settling_counts_the_whole_window_when_never_settled() -> None:
    t = np.arange(1000) * 1e-2
    q = np.full((1000, 1), np.radians(3.0))
    m = run_metrics(t, q, np.zeros_like(q), disturbance_time_s=2.0)
    assert m["settle_s"] == pytest.approx(8.0)


def test_composite_normalizes_per_condition_and_eta() -> None:
    a = {"rmse": 1, "mae": 1, "p95": 1, "peak": 1, "settle_s": 1, "dedt_rms": 1}
    b = {k: 0.5 * v for k, v in a.items()}
    scores = composite_scores({("pd/fb", "C1"): a, ("pd/hmpc", "C1"): b})
    assert scores["pd/fb"] == pytest.approx(sum(WEIGHTS))
    assert scores["pd/hmpc"] == pytest.approx(0.5 * sum(WEIGHTS))
    assert improvement(scores["pd/hmpc"], scores["pd/fb"]) == pytest.approx(0.5)


def test_failed_runs_do_not_set_the_normalization() -> None:
    good = {"rmse": 1, "mae": 1, "p95": 1, "peak": 1, "settle_s": 1, "dedt_rms": 1}
    exploded = {k: 1e6 for k in good}
    metrics = {("pd/fb", "C1"): good, ("pd/lmpc", "C1"): exploded}
    assert composite_scores(metrics)["pd/fb"] == pytest.approx(1e-6 * sum(WEIGHTS))
    scores = composite_scores(metrics, failed={("pd/lmpc", "C1")})
    assert scores["pd/fb"] == pytest.approx(sum(WEIGHTS))
    assert scores["pd/lmpc"] == pytest.approx(1e6 * sum(WEIGHTS))
