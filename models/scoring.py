"""The paper's scoring (Sec. IV-C), with the readings stated in docs/scoring.md.

Six smaller-is-better metrics on the joint tracking error e = q_ref - q in degrees:

- ``rmse``, ``mae``, ``p95``, ``peak``: over all joints and samples pooled.
- ``settle_s``: time after the disturbance until the joint-averaged error mean_j |e_j(t)| (the
  "average joint tracking error" of the paper's Fig. 5) enters and stays within 1 deg; a run that
  never settles scores the whole remaining window.
- ``dedt_rms``: RMS of de/dt (deg/s), all joints pooled.

Composite: on each condition, each metric is divided by its largest value among the configurations
compared (runs that left the limits excluded from that maximum), weighted by
[0.1, 0.1, 0.1, 0.1, 0.3, 0.3] and summed; scores are averaged over conditions.
eta = 1 - score / score_FB for the same law.
"""

from __future__ import annotations

import numpy as np

METRICS = ("rmse", "mae", "p95", "peak", "settle_s", "dedt_rms")
WEIGHTS = (0.1, 0.1, 0.1, 0.1, 0.3, 0.3)
SETTLE_TOLERANCE_DEG = 1.0


def run_metrics(
    t_s: np.ndarray, q: np.ndarray, q_ref: np.ndarray, disturbance_time_s: float | None
) -> dict[str, float]:
    """The six metrics of one run; q, q_ref are (T, N) in radians."""
    e = np.degrees(q_ref - q)
    abs_e = np.abs(e)
    dt = float(t_s[1] - t_s[0])
    mean_abs = abs_e.mean(axis=1)
    start = 0.0 if disturbance_time_s is None else disturbance_time_s
    after = t_s >= start - 1e-12
    outside = np.flatnonzero(after & (mean_abs > SETTLE_TOLERANCE_DEG))
    if outside.size == 0:
        settle = 0.0
    elif outside[-1] == t_s.size - 1:
        settle = float(t_s[-1] + dt - start)  # never settled: the whole window
    else:
        settle = float(t_s[outside[-1] + 1] - start)
    return {
        "rmse": float(np.sqrt(np.mean(e**2))),
        "mae": float(np.mean(abs_e)),
        "p95": float(np.percentile(abs_e, 95)),
        "peak": float(np.max(abs_e)),
        "settle_s": settle,
        "dedt_rms": float(np.sqrt(np.mean((np.diff(e, axis=0) / dt) ** 2))),
    }


def composite_scores(
    metrics: dict[tuple[str, str], dict[str, float]], failed: set[tuple[str, str]] | None = None
) -> dict[str, float]:
    """Composite score per configuration from ``{(configuration, condition): metrics}``.

    Runs in ``failed`` (diverged, or outside the joint limits) do not set the normalization: one
    exploding run would otherwise squash every other score towards zero. They are still scored
    against it (their normalized metrics exceed 1), and the table marks them.
    """
    failed = failed or set()
    configs = sorted({c for c, _ in metrics})
    conditions = sorted({k for _, k in metrics})
    totals = dict.fromkeys(configs, 0.0)
    for condition in conditions:
        present = [c for c in configs if (c, condition) in metrics]
        reference = [c for c in present if (c, condition) not in failed] or present
        for name, weight in zip(METRICS, WEIGHTS, strict=True):
            largest = max(metrics[(c, condition)][name] for c in reference)
            for c in present:
                value = metrics[(c, condition)][name]
                totals[c] += weight * (value / largest if largest > 0 else 0.0) / len(conditions)
    return totals


def improvement(score: float, score_fb: float) -> float:
    """eta = 1 - score / score_FB."""
    return 1.0 - score / score_fb if score_fb > 0 else 0.0
