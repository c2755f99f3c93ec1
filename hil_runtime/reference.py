"""The reference the loop tracks, precomputed per period: a ramp, then a condition, then hold.

- ``hold``: the measured start pose, zero velocity and acceleration, forever.
- ``condition``: a quintic ramp from the measured pose (at rest) onto the condition's start
  (its position, velocity and acceleration at t = 0), never a step; then the condition from its
  t = 0; after its end, its last position held at rest.

The ramp lasts at least ``ramp_s`` and is lengthened until its peak speed is within
``speed_fraction`` of every joint's velocity limit. The whole table is computed before ACTIVE
(5 s at 1 kHz: 5000 rows, 0.7 MB), so a cycle reads row ``k`` and allocates nothing. The
condition's rows (:class:`ConditionTable`: up to an hour, ~0.5 GB and ~1.6 s at 1 kHz) are built
once before the drives are ever enabled; activation adds only the ramp from the measured pose,
so the drives never wait at zero torque while a long table is computed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hil_runtime.conditions import Condition

_MAX_LENGTHEN = 40


def quintic(
    p0: np.ndarray, p1: np.ndarray, v1: np.ndarray, a1: np.ndarray, duration_s: float, t_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rest at p0 (t = 0) to (p1, v1, a1) at t = duration_s: (q, qd, qdd), shaped t.shape + (N,)."""
    T = duration_s
    h = p1 - p0
    c3 = (20 * h - 8 * v1 * T + a1 * T**2) / (2 * T**3)
    c4 = (-30 * h + 14 * v1 * T - 2 * a1 * T**2) / (2 * T**4)
    c5 = (12 * h - 6 * v1 * T + a1 * T**2) / (2 * T**5)
    t = np.asarray(t_s, float)[..., None]
    q = p0 + c3 * t**3 + c4 * t**4 + c5 * t**5
    qd = 3 * c3 * t**2 + 4 * c4 * t**3 + 5 * c5 * t**4
    qdd = 6 * c3 * t + 12 * c4 * t**2 + 20 * c5 * t**3
    return q, qd, qdd


@dataclass(frozen=True)
class ConditionTable:
    """A condition sampled once per period from its t = 0 to its end: (K, N) rows each."""

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    name: str

    @classmethod
    def build(cls, condition: Condition, period_s: float) -> ConditionTable:
        n_cond = int(math.floor(condition.duration_s / period_s + 1e-9)) + 1
        q, qd, qdd = (np.ascontiguousarray(x, float) for x in condition.reference(np.arange(n_cond) * period_s))
        return cls(q, qd, qdd, condition.name)


class Reference:
    """Rows 0..ramp_cycles-1 the ramp, then the table's rows, then the table's last position at rest."""

    def __init__(
        self, ramp: tuple[np.ndarray, np.ndarray, np.ndarray], table: ConditionTable, ramp_cycles: int, name: str
    ) -> None:
        self._ramp_q, self._ramp_qd, self._ramp_qdd = ramp
        self._table = table
        self.ramp_cycles = ramp_cycles
        self.name = name
        self._table_rows = table.q.shape[0]
        self.cycles = ramp_cycles + self._table_rows
        self._hold_q = table.q[-1].copy()
        self._zeros = np.zeros_like(self._hold_q)

    def at(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q_d, qd_d, qdd_d) for period ``k`` since activation (views; do not write)."""
        if k < self.ramp_cycles:
            return self._ramp_q[k], self._ramp_qd[k], self._ramp_qdd[k]
        j = k - self.ramp_cycles
        if j < self._table_rows:
            table = self._table
            return table.q[j], table.qd[j], table.qdd[j]
        return self._hold_q, self._zeros, self._zeros

    # Whole-table views for inspection and tests (copies; the loop reads rows through ``at``).
    @property
    def q(self) -> np.ndarray:
        return np.concatenate([self._ramp_q, self._table.q])

    @property
    def qd(self) -> np.ndarray:
        return np.concatenate([self._ramp_qd, self._table.qd])

    @property
    def qdd(self) -> np.ndarray:
        return np.concatenate([self._ramp_qdd, self._table.qdd])

    @classmethod
    def hold(cls, q0: np.ndarray) -> Reference:
        q0 = np.asarray(q0, float).reshape(1, -1).copy()
        empty = np.zeros((0, q0.shape[1]))
        return cls((empty, empty, empty), ConditionTable(q0, np.zeros_like(q0), np.zeros_like(q0), "hold"), 0, "hold")

    @classmethod
    def condition_only(cls, condition: Condition, period_s: float, table: ConditionTable | None = None) -> Reference:
        """The condition from its t = 0, no ramp (the plant starts on it), then its end held.
        ``table``: the condition's rows built beforehand (:meth:`ConditionTable.build`)."""
        table = table or ConditionTable.build(condition, period_s)
        empty = np.zeros((0, condition.n_joints))
        return cls((empty, empty, empty), table, 0, condition.name)

    @classmethod
    def ramp_then(
        cls,
        q0: np.ndarray,
        condition: Condition,
        period_s: float,
        ramp_s: float,
        velocity_limit_rad_s: np.ndarray,
        speed_fraction: float = 0.25,
        table: ConditionTable | None = None,
    ) -> Reference:
        """A quintic ramp from the measured pose ``q0`` onto the condition, then the condition;
        ``table``: its rows built beforehand (:meth:`ConditionTable.build`), else built here."""
        q0 = np.asarray(q0, float)
        if condition.n_joints != q0.shape[0]:
            raise ValueError(f"condition {condition.name} has {condition.n_joints} joints, the arm {q0.shape[0]}")
        p1, v1, a1 = (np.asarray(x, float) for x in condition.reference(0.0))
        duration = ramp_duration_s(
            q0, p1, v1, a1, ramp_s, np.asarray(velocity_limit_rad_s, float) * speed_fraction, period_s
        )
        n_ramp = round(duration / period_s)
        table = table or ConditionTable.build(condition, period_s)
        if n_ramp == 0:  # already on the condition's start, at its velocity
            empty = np.zeros((0, q0.shape[0]))
            return cls((empty, empty, empty), table, 0, condition.name)
        rq, rqd, rqdd = quintic(q0, p1, v1, a1, duration, np.arange(n_ramp) * period_s)
        ramp = (np.ascontiguousarray(rq), np.ascontiguousarray(rqd), np.ascontiguousarray(rqdd))
        return cls(ramp, table, n_ramp, condition.name)


def ramp_duration_s(
    q0: np.ndarray,
    p1: np.ndarray,
    v1: np.ndarray,
    a1: np.ndarray,
    min_s: float,
    max_speed_rad_s: np.ndarray,
    period_s: float,
) -> float:
    """The shortest whole number of periods >= min_s whose quintic ramp stays below max_speed."""
    if np.all(np.abs(p1 - q0) < 1e-12) and np.all(np.abs(v1) < 1e-12) and np.all(np.abs(a1) < 1e-12) and min_s == 0:
        return 0.0
    # Rest-to-rest quintic peaks at 1.875 h / T: start there, then check numerically.
    duration = max(min_s, float(np.max(1.875 * np.abs(p1 - q0) / max_speed_rad_s)), 10 * period_s)
    for _ in range(_MAX_LENGTHEN):
        duration = math.ceil(duration / period_s - 1e-9) * period_s
        _, qd, _ = quintic(q0, p1, v1, a1, duration, np.linspace(0.0, duration, 201))
        if np.all(np.abs(qd) <= np.maximum(max_speed_rad_s, np.abs(v1)) + 1e-12):
            return duration
        duration *= 1.25
    return duration
