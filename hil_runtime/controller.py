"""The controller: the loaded policy bundle, one onnxruntime call per cycle.

- ``lmpc``: the bundle's fused graph as exported (feedback law + torque emulator + trust region +
  saturation); the command is its ``tau``.
- ``fb``: the same graph, but the command is the feedback law's own torque ``tau_fb`` (saturated
  here), the baseline the paper compares against. The graph computes both in one call, so the two
  modes cost the same.

Either way the law's next state records the torque the supervisor actually commanded
(:meth:`Controller.commit`), not the graph's guess: for ADRC the applied torque feeds its
observer (the manifest's ``law.applied_torque_slice``).

``torque_rate_limit="libfranka"`` (config ``bundle.torque_rate_limit``; lmpc mode only, the law's
own torque in fb mode is the paper's baseline, untouched): the LMPC torque's change per cycle is
clamped per joint to libfranka's rate bound (:mod:`hil_runtime.rate_limit`) against the torque
last committed, reset on activation to the torque the drives hold (:meth:`Controller.reset`).

``velocity_filter_hz`` (config ``bundle.velocity_filter_hz``; lmpc mode only): the measured velocity is
low-passed before the policy (:mod:`hil_runtime.velocity_filter`), reset on activation.

A bundle whose graph reads tau_prev (``bundle.takes_previous_torque``; docs/lmpc.md §11: the emulator
steps from the last command within the rate bound inside the graph) gets the same torque: the one the
supervisor commanded last cycle (:meth:`Controller.commit`), on activation the held set-point
(:meth:`Controller.reset`). In fb mode it is fed too (the command is then the law's), so a switch of
mode never hands the graph a stale torque.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from hil_runtime.bundle import PolicyBundle
from hil_runtime.rate_limit import TORQUE_RATE_LIMITS, TorqueRateLimiter
from hil_runtime.velocity_filter import VelocityFilter

Mode = Literal["lmpc", "fb"]


class Controller:
    def __init__(
        self,
        bundle: PolicyBundle,
        mode: Mode = "lmpc",
        torque_rate_limit: str = "none",
        velocity_filter_hz: float | None = None,
    ) -> None:
        if mode not in ("lmpc", "fb"):
            raise ValueError(f"mode must be 'lmpc' or 'fb', not {mode!r}")
        if torque_rate_limit not in TORQUE_RATE_LIMITS:
            raise ValueError(f"torque_rate_limit must be one of {TORQUE_RATE_LIMITS}, not {torque_rate_limit!r}")
        self.bundle = bundle
        self.mode = mode
        self.n_joints = bundle.n_joints
        applied = bundle.manifest.law.applied_torque_slice
        self._applied = slice(int(applied[0]), int(applied[1])) if applied else None
        self.state = np.zeros(bundle.state_size)
        self._next = np.zeros(bundle.state_size)
        self._trust = bundle.last_trust  # a view of the graph's output row
        self._previous = bundle.previous_torque_nm  # a view of the graph's input row (None: not read)
        self.rate_limiter = (
            TorqueRateLimiter(bundle.torque_rate_nm_s, bundle.period_s)
            if torque_rate_limit == "libfranka" and mode == "lmpc"
            else None
        )
        self.velocity_filter = (
            VelocityFilter(velocity_filter_hz, bundle.period_s, bundle.n_joints)
            if velocity_filter_hz is not None and mode == "lmpc"
            else None
        )

    def reset(self, q0: np.ndarray, held_torque_nm: np.ndarray | None = None) -> None:
        """The law's state at the start of a run from the measured positions; the rate limit (if
        any) starts from ``held_torque_nm``, the torque the drives hold now (None: zero)."""
        self.state[:] = self.bundle.initial_state(np.asarray(q0, float))
        if self.rate_limiter is not None:
            self.rate_limiter.reset(held_torque_nm)
        if self.velocity_filter is not None:
            self.velocity_filter.reset()
        if self._previous is not None:  # the graph steps from the set-point the drives hold now (None: zero)
            self._previous[:] = 0.0 if held_torque_nm is None else np.nan_to_num(np.asarray(held_torque_nm, float))

    def step(
        self, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, float]:
        """(command candidate, tau_fb, fallback) for this cycle; views valid until the next step.

        ``fallback`` is the trust region's 1 - alpha in lmpc mode (0: the emulator's torque, 1: the
        law's), and 0 in fb mode (no trust region is involved).
        """
        if self.velocity_filter is not None:
            qd = self.velocity_filter.filter(qd)
        tau, tau_fb, nxt = self.bundle.step(q, qd, q_d, qd_d, qdd_d, self.state)
        self._next[:] = nxt
        if self.mode == "fb":  # the supervisor saturates it, as it does every candidate
            return tau_fb, tau_fb, 0.0
        if self.rate_limiter is not None:
            tau = self.rate_limiter.limit(tau)
        return tau, tau_fb, float(self._trust[0])

    @property
    def next_state(self) -> np.ndarray:
        """The law's state after this cycle's step, before :meth:`commit` records the applied torque
        (what the supervisor checks: a law whose state went non-finite cannot go on)."""
        return self._next

    def commit(self, applied_torque_nm: np.ndarray) -> None:
        """Advance the law's state, recording the torque actually commanded."""
        if self._applied is not None:
            self._next[self._applied] = applied_torque_nm
        self.state, self._next = self._next, self.state
        if self.rate_limiter is not None:
            self.rate_limiter.commit(applied_torque_nm)
        if self._previous is not None:  # the graph's tau_prev next cycle (the bound input row itself)
            self._previous[:] = applied_torque_nm
