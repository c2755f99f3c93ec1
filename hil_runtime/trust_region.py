"""The trust region's rule in numpy (hil_runtime.bundle's docstring; docs/lmpc.md): the emulator's
guard features and the filter the graph applies inside itself, reproduced here so that the writer's
tests and the safety supervisor can check the graph against it."""

from __future__ import annotations

from typing import Any

import numpy as np

from hil_runtime.bundle_schema import FEATURE_SETS, TRUST_MIN_SPAN, Manifest


def named_features(q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any, tau_fb: Any) -> dict[str, Any]:
    """Every feature a FEATURE_SETS entry may name, from the state and the law's torque. Plain
    arithmetic, so numpy arrays and torch tensors alike (the graph's exporter builds the same)."""
    return {
        "q": q,
        "e": q_d - q,
        "qd": qd,
        "e_dot": qd_d - qd,
        "q_d": q_d,
        "qd_d": qd_d,
        "qdd_d": qdd_d,
        "tau_fb": tau_fb,
    }


def emulator_features(
    feature_set: str,
    q: np.ndarray,
    qd: np.ndarray,
    q_d: np.ndarray,
    qd_d: np.ndarray,
    qdd_d: np.ndarray,
    tau_fb: np.ndarray,
) -> np.ndarray:
    """The emulator input s of ``feature_set`` (FEATURE_SETS), last axis."""
    parts = named_features(q, qd, q_d, qd_d, qdd_d, tau_fb)
    return np.concatenate([np.asarray(parts[k], float) for k in FEATURE_SETS[feature_set]], axis=-1)


def trust_filter(manifest: Manifest, s: np.ndarray, r: np.ndarray, tau_fb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The trust-region rule (module docstring) in numpy: (tau (B, N), trust (B, 2)) from the guard
    features s (B, F) (``emulator_features(GUARD_FEATURES, ...)``), the emulator's residual r (B, N)
    (tau_L_raw - tau_fb for an absolute-target emulator) and tau_fb (B, N). The graph applies the
    same rule; the safety supervisor can re-check with it."""
    limit = np.asarray(manifest.limits.torque_nm, float)
    s, r, tau_fb = np.atleast_2d(s), np.atleast_2d(r), np.atleast_2d(tau_fb)
    trust = manifest.trust_region
    alpha = np.ones(s.shape[0])
    clamped = np.zeros(s.shape[0])
    if trust is not None:
        low, high = np.asarray(trust.feature_low, float), np.asarray(trust.feature_high, float)
        span = np.maximum(high - low, TRUST_MIN_SPAN)
        d = np.max(np.maximum(np.maximum(low - s, s - high), 0.0) / span, axis=1)
        alpha = np.clip(1.0 - d / max(float(trust.box_margin), 1e-12), 0.0, 1.0)
        if trust.residual_bound_nm is not None:
            bound = np.asarray(trust.residual_bound_nm, float)
            clamped = np.sum(np.abs(r) > bound, axis=1).astype(float)
            r = np.clip(r, -bound, bound)
    tau = np.clip(tau_fb + alpha[:, None] * r, -limit, limit)
    return tau, np.stack([1.0 - alpha, np.where(alpha > 0, clamped, 0.0)], 1)
