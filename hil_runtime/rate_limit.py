"""The commanded torque's rate limit, as libfranka applies it client-side (docs/scoring.md, docs/lmpc.md §10).

libfranka rate-limits every commanded joint torque to ``franka::kMaxTorqueRate`` = 1000 N·m/s
(include/franka/rate_limiting.h; ``franka::limitRate`` in its torque-control examples): 1 N·m per
1 ms cycle on the Panda's 87 N·m joints. Scaled by the joint's torque limit, the rule carries to
arms of other sizes (1.17 N·m per ms on ur5_paper's 102 N·m shoulder). This module is the one
definition of that bound: the deployable verdict (``models.effort``), the HMPC's hard rate box
(``models.hmpc``) and the LMPC's output limit below all read it.

The limit itself (:class:`TorqueRateLimiter`), applied to the policy's torque before the supervisor::

    tau_out = tau_prev + clip(tau - tau_prev, -step, step)     per joint, step = max_torque_step_nm

``tau_prev`` is the torque actually commanded last cycle (after the supervisor: :meth:`commit`),
reset on activation to the torque the drives measured/held then (:meth:`reset`). A network cannot be
trusted to learn a hard constraint its teacher had; the bundle's policy stage enforces it instead,
identically in the runtime (``hil_runtime.controller``) and the simulator (``models.lmpc.controller``).
It works on one arm (N,) or a batch (B, N) and allocates nothing per call (buffers made at reset).
A non-finite torque passes through unchanged (the supervisor substitutes the law's, as without the
limit); a non-finite previous torque is never committed (the supervisor's command is finite).

Names (``bundle.torque_rate_limit`` in the runtime config, ``--torque-rate-limit`` of
``hil experiment``): ``none`` (default; the policy's torque as computed) and ``libfranka``.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

FRANKA_MAX_TORQUE_RATE_NM_S = 1000.0  # franka::kMaxTorqueRate, include/franka/rate_limiting.h
FRANKA_TORQUE_LIMIT_NM = 87.0  # the Panda's joints 1-4 (the rate limit is read relative to this)

TorqueRateLimit = Literal["none", "libfranka"]
TORQUE_RATE_LIMITS: tuple[str, ...] = ("none", "libfranka")


def max_torque_step_nm(torque_limit_nm: np.ndarray, period_s: float) -> np.ndarray:
    """The largest commanded torque change per cycle a real arm accepts, per joint (N·m)."""
    rate_nm_s = FRANKA_MAX_TORQUE_RATE_NM_S * np.asarray(torque_limit_nm, float) / FRANKA_TORQUE_LIMIT_NM
    return rate_nm_s * period_s


class TorqueRateLimiter:
    """Clamp each joint's commanded torque change per cycle to ``max_torque_step_nm`` (module docstring).

    ``limited_cycles``: calls in which at least one joint (of any arm) was clamped, since the last reset.
    """

    def __init__(self, torque_limit_nm: np.ndarray, period_s: float) -> None:
        self.step_nm = max_torque_step_nm(torque_limit_nm, period_s)
        self._neg_step_nm = -self.step_nm
        self.previous_nm = np.zeros_like(self.step_nm)
        self._delta = np.zeros_like(self.step_nm)
        self._out = np.zeros_like(self.step_nm)
        self._clamped = np.zeros(self.step_nm.shape, bool)
        self.limited_cycles = 0

    def reset(self, held_torque_nm: np.ndarray | None = None, arms: int | None = None) -> None:
        """Start from the torque the drives hold now (None: zero); ``arms``: B for a batch, None: one arm."""
        shape = self.step_nm.shape if arms is None else (arms, *self.step_nm.shape)
        if self.previous_nm.shape != shape:  # a new batch size: the buffers once, never per cycle
            self.previous_nm = np.zeros(shape)
            self._delta = np.zeros(shape)
            self._out = np.zeros(shape)
            self._clamped = np.zeros(shape, bool)
        if held_torque_nm is None:
            self.previous_nm[...] = 0.0
        else:
            self.previous_nm[...] = np.nan_to_num(np.asarray(held_torque_nm, float))  # a held torque is finite
        self.limited_cycles = 0

    def limit(self, tau_nm: np.ndarray) -> np.ndarray:
        """The rate-limited torque (a view of this limiter's buffer, valid until the next call)."""
        delta, out = self._delta, self._out
        np.subtract(tau_nm, self.previous_nm, out=delta)
        np.minimum(delta, self.step_nm, out=out)
        np.maximum(out, self._neg_step_nm, out=out)
        # NaN compares unequal: a non-finite tau counts, and passes on as NaN
        if np.not_equal(out, delta, out=self._clamped).any():
            self.limited_cycles += 1
        np.add(self.previous_nm, out, out=out)
        return out

    def commit(self, commanded_nm: np.ndarray) -> None:
        """Record the torque actually commanded this cycle (after the supervisor)."""
        self.previous_nm[...] = commanded_nm


__all__ = [
    "FRANKA_MAX_TORQUE_RATE_NM_S",
    "FRANKA_TORQUE_LIMIT_NM",
    "TORQUE_RATE_LIMITS",
    "TorqueRateLimit",
    "TorqueRateLimiter",
    "max_torque_step_nm",
]
