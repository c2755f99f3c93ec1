"""What one HMPC solve returns and the batch data it works on: the status codes, ``HMPCResult``, the fixed
rows of K problems (``Rows``) and their predicted rollouts (``Rollout``), shared by the solver and its tests."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

CONVERGED, NONFINITE_INPUT, NOT_CONVERGED, NONFINITE_SOLUTION = 0, 1, 2, 3
STATUS_NAMES = {
    CONVERGED: "converged",
    NONFINITE_INPUT: "nonfinite_input",
    NOT_CONVERGED: "not_converged",
    NONFINITE_SOLUTION: "nonfinite_solution",
}


@dataclass
class HMPCResult:
    """One batch solve. Arrays are per state (leading axis B)."""

    tau_nm: np.ndarray  # (B, N) torque to apply: the optimum's first step, or the fallback
    tau_fb_nm: np.ndarray  # (B, N) the law's torque
    law_state: np.ndarray  # (B, S) the law's next state, with the applied torque recorded
    sequence_nm: np.ndarray  # (B, T, N) optimized torque sequence (NaN rows where there was none)
    status: np.ndarray  # (B,) int, see STATUS_NAMES
    fell_back: np.ndarray  # (B,) bool: tau_nm is the fallback torque
    cost: np.ndarray  # (B,) cost of the returned sequence (NaN when none)
    candidate_cost: np.ndarray  # (B,) cost of the best of the paper's candidates w * tau_fb
    iterations: np.ndarray  # (B,) Gauss-Newton iterations used
    anchor_scale: np.ndarray | None = None  # (B,) w* of the anchored cost (NaN where not solved); None: absolute cost


@dataclass
class Rows:
    """The fixed data of K problems: start state, reference preview, the law's state at k+1."""

    q0: np.ndarray  # (K, N)
    qd0: np.ndarray
    ref_q: np.ndarray  # (K, T, N)
    ref_qd: np.ndarray
    qdd_d: np.ndarray  # (K, N), held over the preview
    law_state: np.ndarray  # (K, S)
    anchor: np.ndarray | None = None  # (K, T, N) torque the W2 term is measured from (anchored cost), None: 0
    previous: np.ndarray | None = None  # (K, N) tau_0, the torque applied last cycle (smoothness term)
    lower: np.ndarray | None = None  # (K, T, N) the torque box of each step (the rate limit), None: the limits
    upper: np.ndarray | None = None
    rate_weight: np.ndarray | None = None  # (K, N, N) c dt^2 M(q)^-2 of the smoothness term, None: no term

    def _map(self, fn: Callable[[np.ndarray], np.ndarray]) -> Rows:
        """The same rows with ``fn`` applied to every array (row selection, repetition)."""
        return Rows(
            fn(self.q0),
            fn(self.qd0),
            fn(self.ref_q),
            fn(self.ref_qd),
            fn(self.qdd_d),
            fn(self.law_state),
            None if self.anchor is None else fn(self.anchor),
            None if self.previous is None else fn(self.previous),
            None if self.lower is None else fn(self.lower),
            None if self.upper is None else fn(self.upper),
            None if self.rate_weight is None else fn(self.rate_weight),
        )

    def take(self, index: np.ndarray) -> Rows:
        return self._map(lambda a: a[index])

    def repeat(self, count: int) -> Rows:
        return self._map(lambda a: np.repeat(a, count, axis=0))

    def deviation(self, u: np.ndarray) -> np.ndarray:
        """What W2 weighs: u itself (absolute cost) or u - anchor (anchored cost)."""
        return u if self.anchor is None else np.ascontiguousarray(u - self.anchor)


@dataclass
class Rollout:
    q: np.ndarray  # (K, T, N) predicted states at k+1..k+T
    qd: np.ndarray
    features: np.ndarray  # (K, T, nE) E(k+j)
    law_states: np.ndarray | None  # (K, T, S) the law's state at k+j (law-specific features only)
    cost: np.ndarray  # (K,)

    def take(self, index: np.ndarray) -> Rollout:
        states = None if self.law_states is None else self.law_states[index]
        return Rollout(self.q[index], self.qd[index], self.features[index], states, self.cost[index])

    def put(self, index: np.ndarray, other: Rollout) -> None:
        self.q[index], self.qd[index], self.features[index], self.cost[index] = (
            other.q,
            other.qd,
            other.features,
            other.cost,
        )
        if self.law_states is not None and other.law_states is not None:
            self.law_states[index] = other.law_states
