"""The commanded torque's rate bound, per robot, as libfranka applies it client-side (docs/scoring.md,
docs/lmpc.md §10, docs/any_arm.md "Torque-rate bound").

libfranka rate-limits every commanded joint torque to ``franka::kMaxTorqueRate`` = 1000 N·m/s on all
seven Panda joints (include/franka/rate_limiting.h; ``franka::limitRate`` in its torque-control
examples): 1 N·m per 1 ms cycle. This module is the one definition of the bound: the deployable
verdict (``models.effort``), the HMPC's hard rate box (``models.hmpc``) and the LMPC's output limit
below all read :func:`max_torque_step_nm` of the same per-joint rate.

Where a robot's rate comes from (:func:`torque_rate_limit_nm_s`, one rule per robot):

- the robot registry (``models/robots/data/robots.yaml``, ``torque_rate``): ``panda`` 1000 N·m/s
  (libfranka's kMaxTorqueRate, unscaled); ``ur5`` 1000 N·m/s (Universal Robots publish no torque-rate
  limit for ``direct_torque``: libfranka's figure, docs/any_arm.md); ``ur5_paper`` ``scaled``
  (1000 N·m/s per 87 N·m of the joint's torque limit, 1.17 N·m per ms on its 102 N·m shoulder: the
  rule its bundles and published tables were measured with);
- any other URDF: ``DEFAULT_TORQUE_RATE_NM_S`` (1000 N·m/s on every joint);
- a bundle: its manifest's ``limits.torque_rate_nm_s`` (written from the robot at export); a manifest
  written before that field existed was made under the ``scaled`` rule, which it keeps.

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

FRANKA_MAX_TORQUE_RATE_NM_S = 1000.0  # franka::kMaxTorqueRate, include/franka/rate_limiting.h (every joint)
FRANKA_TORQUE_LIMIT_NM = 87.0  # the Panda's joints 1-4 (the "scaled" rule reads the rate relative to this)
DEFAULT_TORQUE_RATE_NM_S = FRANKA_MAX_TORQUE_RATE_NM_S  # a URDF with no registry entry
#: the rule name for 1000 N·m/s per 87 N·m of each joint's torque limit (ur5_paper's bundles and tables)
SCALED_RULE = "scaled"

#: a robot's rate as given: N·m/s for every joint, one per joint, or ``SCALED_RULE``
TorqueRate = float | list[float] | tuple[float, ...] | str

TorqueRateLimit = Literal["none", "libfranka"]
TORQUE_RATE_LIMITS: tuple[str, ...] = ("none", "libfranka")


def torque_rate_limit_nm_s(rate: TorqueRate | None, torque_limit_nm: np.ndarray) -> np.ndarray:
    """Each joint's torque-rate bound (N·m/s) from a robot's rule (module docstring); ``None``: the
    default. Raises ValueError on a rule that is not a positive finite rate, a list of N or ``scaled``."""
    limit = np.asarray(torque_limit_nm, float)
    if rate is None:
        rate = DEFAULT_TORQUE_RATE_NM_S
    if isinstance(rate, str):
        if rate != SCALED_RULE:
            raise ValueError(
                f"torque rate: unknown rule '{rate}' (a rate in N·m/s, a list per joint or '{SCALED_RULE}')"
            )
        return FRANKA_MAX_TORQUE_RATE_NM_S * limit / FRANKA_TORQUE_LIMIT_NM
    try:
        values = np.broadcast_to(np.asarray(rate, float), limit.shape).copy()
    except (TypeError, ValueError):
        raise ValueError(f"torque rate: expected one rate or {limit.size} (N·m/s), got {rate!r}") from None
    if not np.all(np.isfinite(values) & (values > 0)):
        raise ValueError(f"torque rate: every rate must be positive and finite, got {rate!r}")
    return values


def max_torque_step_nm(torque_rate_nm_s: np.ndarray, period_s: float) -> np.ndarray:
    """The largest commanded torque change per cycle a real arm accepts, per joint (N·m): the robot's
    torque-rate bound (:func:`torque_rate_limit_nm_s`) times the period."""
    return np.asarray(torque_rate_nm_s, float) * period_s


class TorqueRateLimiter:
    """Clamp each joint's commanded torque change per cycle to ``max_torque_step_nm`` (module docstring).

    ``limited_cycles``: calls in which at least one joint (of any arm) was clamped, since the last reset.
    """

    def __init__(self, torque_rate_nm_s: np.ndarray, period_s: float) -> None:
        self.step_nm = max_torque_step_nm(torque_rate_nm_s, period_s)
        self._neg_step_nm = -self.step_nm
        self.previous_nm = np.zeros_like(self.step_nm)
        self._delta = np.zeros_like(self.step_nm)
        self._out = np.zeros_like(self.step_nm)
        self.limited_cycles = 0

    def reset(self, held_torque_nm: np.ndarray | None = None, arms: int | None = None) -> None:
        """Start from the torque the drives hold now (None: zero); ``arms``: B for a batch, None: one arm."""
        shape = self.step_nm.shape if arms is None else (arms, *self.step_nm.shape)
        if self.previous_nm.shape != shape:  # a new batch size: the buffers once, never per cycle
            self.previous_nm = np.zeros(shape)
            self._delta = np.zeros(shape)
            self._out = np.zeros(shape)
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
        # A clamp only shrinks a change, so |out|^2 < |delta|^2 exactly when one acted (NaN: unequal,
        # counted, passed on as NaN); two dot products cost less than a comparison and a reduction.
        if np.vdot(out, out) != np.vdot(delta, delta):
            self.limited_cycles += 1
        np.add(self.previous_nm, out, out=out)
        return out

    def commit(self, commanded_nm: np.ndarray) -> None:
        """Record the torque actually commanded this cycle (after the supervisor)."""
        self.previous_nm[...] = commanded_nm


__all__ = [
    "DEFAULT_TORQUE_RATE_NM_S",
    "FRANKA_MAX_TORQUE_RATE_NM_S",
    "FRANKA_TORQUE_LIMIT_NM",
    "SCALED_RULE",
    "TORQUE_RATE_LIMITS",
    "TorqueRateLimit",
    "TorqueRate",
    "TorqueRateLimiter",
    "max_torque_step_nm",
    "torque_rate_limit_nm_s",
]
