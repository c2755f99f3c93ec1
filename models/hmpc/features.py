"""The HMPC's cost pieces that depend only on the law and the rollout (models.hmpc.solver uses
them): the torque changes the smoothness term weighs, a law's own error features along the
preview and their Jacobian."""

from __future__ import annotations

import numpy as np

from models.feedback.base import FeedbackLaw
from models.hmpc.result import Rollout, Rows

FEATURE_FD_STEP = 1e-6  # central differences of a law's own error features (linear in practice)


def torque_changes(rows: Rows, u: np.ndarray) -> np.ndarray:
    """tau_j - tau_{j-1} (K, T, N), tau_0 = rows.previous."""
    assert rows.previous is not None
    change = np.empty_like(u)
    np.subtract(u[:, 0], rows.previous, out=change[:, 0])
    np.subtract(u[:, 1:], u[:, :-1], out=change[:, 1:])
    return change


def law_features(
    law: FeedbackLaw, horizon: int, rows: Rows, u: np.ndarray, q_path: np.ndarray, qd_path: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The law's own E along the preview, its state stepped with the predicted measurements."""
    state = law.with_applied_torque(rows.law_state, u[:, 0])
    features, states = [], []
    for j in range(horizon):
        states.append(state)
        args = (q_path[:, j], qd_path[:, j], rows.ref_q[:, j], rows.ref_qd[:, j])
        features.append(np.asarray(law.error_features(np, state, *args), float))
        if j + 1 < horizon:
            state = law.with_applied_torque(np.asarray(law.step(np, state, *args, rows.qdd_d)[1], float), u[:, j + 1])
    return np.stack(features, 1), np.stack(states, 1)


def feature_jacobian(law: FeedbackLaw, rows: Rows, state: Rollout) -> np.ndarray:
    """dE/dx (K, T, nE, 2N) of a law's own features at fixed law state, by central differences."""
    k, horizon, n = state.q.shape
    x = np.concatenate([state.q, state.qd], -1).reshape(k * horizon, 2 * n)
    if state.law_states is None:
        raise ValueError("hmpc: feature Jacobian of a rollout without the law's states (base features)")
    law_state = state.law_states.reshape(k * horizon, -1)
    ref_q, ref_qd = rows.ref_q.reshape(-1, n), rows.ref_qd.reshape(-1, n)
    h = FEATURE_FD_STEP * np.maximum(1.0, np.abs(x))
    delta = np.eye(2 * n)[None] * h[:, None, :]  # (KT, 2N perturbations, 2N)
    xs = np.concatenate([x[:, None] + delta, x[:, None] - delta], 1).reshape(-1, 2 * n)
    rep = 4 * n
    values = np.asarray(
        law.error_features(
            np,
            np.repeat(law_state, rep, 0),
            xs[:, :n],
            xs[:, n:],
            np.repeat(ref_q, rep, 0),
            np.repeat(ref_qd, rep, 0),
        ),
        float,
    )
    values = values.reshape(k * horizon, 2, 2 * n, -1)
    jac: np.ndarray = (values[:, 0] - values[:, 1]) / (2.0 * h[:, :, None])  # (KT, 2N, nE)
    return np.swapaxes(jac, 1, 2).reshape(k, horizon, -1, 2 * n)
