"""The LMPC's velocity input filter: a first-order low-pass on the measured joint velocity before the policy.

The static LMPC's torque moves 26–35 N·m per rad/s of velocity error on ur5_paper's shoulder (its learned
damping: hil_runtime.bundle_probes.velocity_sensitivity), so a drive's velocity noise goes straight into
the torque: at the issue's 0.2 rad/s it chatters 8.5 N·m RMS per cycle where the law chatters 1.4–1.9.
A low-pass on that input, as a servo drive's own velocity filter does, cuts the cycle-to-cycle change of
the noise by (1 − a) √(2 / (1 + a)) / √2 (a = exp(−2π f_c T); 0.21 at 50 Hz and 1 kHz) at the price of a
phase lag of atan(ω / 2π f_c) in the damping (9° at 8 Hz for 50 Hz). docs/lmpc.md section 13: the
measured trade-off.

    y_k = a y_(k-1) + (1 − a) qd_k,   y_0 = qd_0 (the first sample after a reset passes unfiltered)

One implementation for the runtime's policy stage (``bundle.velocity_filter_hz``, hil_runtime.controller,
lmpc mode only: the law's baseline in fb mode sees the raw velocity) and the simulator's LMPC
(models.lmpc.controller), on one arm (N,) or a batch (B, N); it allocates nothing per call. A non-finite
sample is passed on (the supervisor then sees it) and not kept: the filter's state stays finite.
"""

from __future__ import annotations

import math

import numpy as np


def filter_pole(cutoff_hz: float, period_s: float) -> float:
    """a = exp(−2π f_c T), the exact discretization of a first-order low-pass at ``cutoff_hz``; ValueError
    unless 0 < f_c < the Nyquist rate 1 / (2T)."""
    if not (math.isfinite(cutoff_hz) and 0.0 < cutoff_hz < 0.5 / period_s):
        raise ValueError(
            f"velocity filter: cutoff {cutoff_hz!r} Hz must be above 0 and below the Nyquist rate {0.5 / period_s:g} Hz"
        )
    return math.exp(-2.0 * math.pi * cutoff_hz * period_s)


def step_noise_gain(pole: float) -> float:
    """The RMS cycle-to-cycle change of the filter's output per unit RMS of white input noise,
    (1 − a) √(2 / (1 + a)): √2 with no filter (a = 0)."""
    return (1.0 - pole) * math.sqrt(2.0 / (1.0 + pole))


class VelocityFilter:
    """y = a y + (1 − a) qd per joint (module docstring); :meth:`reset` before a run."""

    def __init__(self, cutoff_hz: float, period_s: float, n_joints: int) -> None:
        self.cutoff_hz = float(cutoff_hz)
        self.pole = filter_pole(cutoff_hz, period_s)
        self._gain = 1.0 - self.pole
        self.state = np.zeros(n_joints)
        self._scratch = np.zeros(n_joints)
        self._primed = False

    def reset(self, arms: int | None = None) -> None:
        """Forget the past: the next sample passes unfiltered. ``arms``: B for a batch, None: one arm."""
        n = self.state.shape[-1]
        shape = (n,) if arms is None else (arms, n)
        if self.state.shape != shape:  # a new batch size: the buffers once, never per cycle
            self.state = np.zeros(shape)
            self._scratch = np.zeros(shape)
        self._primed = False

    def filter(self, qd: np.ndarray) -> np.ndarray:
        """The filtered velocity (a view of this filter's state, valid until the next call)."""
        if not self._primed:
            np.copyto(self.state, qd)
            if np.isfinite(self.state).all():
                self._primed = True
                return self.state
            np.copyto(self._scratch, qd)
            self.state[...] = 0.0
            return self._scratch
        np.subtract(qd, self.state, out=self._scratch)
        self._scratch *= self._gain
        if not math.isfinite(self._scratch.sum()):  # passed on, not kept (a sum: no per-cycle array)
            np.copyto(self._scratch, qd)
            return self._scratch
        self.state += self._scratch
        return self.state


__all__ = ["VelocityFilter", "filter_pole", "step_noise_gain"]
