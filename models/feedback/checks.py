"""``check_law``: does a feedback law keep the promises of :class:`~models.feedback.base.FeedbackLaw`?

In the manner of Gymnasium's ``check_env``: one public check any law (the six here, a new one)
runs against before the simulator, the HMPC, the dataset and the ONNX export rely on it. It checks

- the declarations: ``name``, ``n_joints``, ``period_s``, ``torque_limit_nm``, ``state_size``,
  JSON-serializable ``params``, ``applied_torque_slice`` inside the state;
- ``initial_state`` (B, S) finite; ``step`` on (B, ...) numpy arrays returns (tau (B, N), state (B, S)),
  finite and saturated to the torque limits, also for huge errors;
- purity: inputs untouched, the same inputs give the same outputs, a batch is its rows one at a time;
- with torch installed, the same definition in torch (float64) equals numpy: what the ONNX export traces.

It raises :class:`LawCheckError` naming the law and the first broken promise.
"""

from __future__ import annotations

import json

import numpy as np

from models.feedback.base import FeedbackLaw

__all__ = ["LawCheckError", "check_law"]


class LawCheckError(AssertionError):
    """The law under check broke a promise of FeedbackLaw (the message says which)."""


def check_law(law: FeedbackLaw, batch: int = 4, seed: int = 0, torch_atol: float = 1e-9) -> None:
    """Check ``law`` on ``batch`` random states (seeded); ``torch_atol``: numpy vs torch, N m."""
    label = f"law '{getattr(law, 'name', type(law).__name__)}'"

    def require(condition: bool, message: str) -> None:
        if not condition:
            raise LawCheckError(f"{label}: {message}")

    require(isinstance(law, FeedbackLaw), f"{type(law).__name__} is not a FeedbackLaw")
    require(isinstance(law.name, str) and law.name != "", "name is empty")
    n, s = law.n_joints, law.state_size
    require(isinstance(n, int) and n > 0, f"n_joints is {n!r}")
    require(isinstance(s, int) and s >= 0, f"state_size is {s!r}")
    require(np.isfinite(law.period_s) and law.period_s > 0, f"period_s is {law.period_s!r}")
    limit = np.asarray(law.torque_limit_nm)
    require(limit.shape == (n,) and bool(np.all(limit > 0)), f"torque_limit_nm {limit.tolist()} is not ({n},) > 0")
    try:
        json.dumps(law.params, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise LawCheckError(f"{label}: params are not plain JSON ({exc})") from None
    applied = law.applied_torque_slice
    if applied is not None:
        require(len(range(s)[applied]) == n, f"applied_torque_slice {applied} does not hold {n} values of the state")

    rng = np.random.default_rng(seed)
    q, qd, q_d, qd_d, qdd_d = (0.3 * rng.normal(size=(batch, n)) for _ in range(5))
    state0 = law.initial_state(q)
    require(
        isinstance(state0, np.ndarray) and state0.shape == (batch, s) and bool(np.all(np.isfinite(state0))),
        f"initial_state(q0 ({batch}, {n})) is not a finite ({batch}, {s}) array",
    )
    state = state0 + 0.01 * rng.normal(size=state0.shape)
    inputs = (state, q, qd, q_d, qd_d, qdd_d)
    copies = [a.copy() for a in inputs]
    tau, next_state = law.step(np, *inputs)
    require(all(np.array_equal(a, b) for a, b in zip(inputs, copies, strict=True)), "step changed its inputs")
    for name, value, shape in (("tau", tau, (batch, n)), ("next state", next_state, (batch, s))):
        require(
            isinstance(value, np.ndarray) and value.shape == shape and bool(np.all(np.isfinite(value))),
            f"step: {name} is not a finite {shape} array",
        )
    require(bool(np.all(np.abs(tau) <= limit + 1e-12)), "step: tau exceeds the torque limits")
    tau2, next2 = law.step(np, *copies)
    require(np.array_equal(tau, tau2) and np.array_equal(next_state, next2), "step is not deterministic")
    for b in range(batch):
        row = [a[b : b + 1] for a in inputs]
        tau_b, next_b = law.step(np, *row)
        require(
            np.allclose(tau_b[0], tau[b], rtol=1e-12, atol=1e-12)
            and np.allclose(next_b[0], next_state[b], rtol=1e-12, atol=1e-12),
            f"step: row {b} alone differs from row {b} of the batch",
        )
    huge = law.step(np, state, 1e3 * q, 1e3 * qd, q_d, qd_d, qdd_d)
    require(
        bool(np.all(np.isfinite(huge[0])) and np.all(np.isfinite(huge[1])))
        and bool(np.all(np.abs(huge[0]) <= limit + 1e-12)),
        "step: huge errors give non-finite or unsaturated torques",
    )

    try:
        import torch
    except ImportError:  # the torch form is checked where torch is installed (the models extra)
        return
    with torch.no_grad():
        tau_t, next_t = law.step(torch, *(torch.as_tensor(a, dtype=torch.float64) for a in inputs))
    gap = max(float(np.max(np.abs(tau_t.numpy() - tau))), float(np.max(np.abs(next_t.numpy() - next_state), initial=0)))
    require(gap <= torch_atol, f"step in torch differs from numpy by {gap:.3g} (> {torch_atol:g})")
