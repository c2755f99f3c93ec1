"""The controller: the loaded policy bundle, one onnxruntime call per cycle.

- ``lmpc``: the bundle's fused graph as exported (feedback law + torque emulator + trust region +
  saturation); the command is its ``tau``.
- ``fb``: the same graph, but the command is the feedback law's own torque ``tau_fb`` (saturated
  here), the baseline the paper compares against. The graph computes both in one call, so the two
  modes cost the same.

Either way the law's next state records the torque the supervisor actually commanded
(:meth:`Controller.commit`), not the graph's guess: for ADRC the applied torque feeds its
observer (the manifest's ``law.applied_torque_slice``).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from hil_runtime.bundle import PolicyBundle

Mode = Literal["lmpc", "fb"]


class Controller:
    def __init__(self, bundle: PolicyBundle, mode: Mode = "lmpc") -> None:
        if mode not in ("lmpc", "fb"):
            raise ValueError(f"mode must be 'lmpc' or 'fb', not {mode!r}")
        self.bundle = bundle
        self.mode = mode
        self.n_joints = bundle.n_joints
        applied = bundle.manifest.law.applied_torque_slice
        self._applied = slice(int(applied[0]), int(applied[1])) if applied else None
        self.state = np.zeros(bundle.state_size)
        self._next = np.zeros(bundle.state_size)
        self._trust = bundle.last_trust  # a view of the graph's output row

    def reset(self, q0: np.ndarray) -> None:
        """The law's state at the start of a run from the measured positions."""
        self.state[:] = self.bundle.initial_state(np.asarray(q0, float))

    def step(
        self, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, float]:
        """(command candidate, tau_fb, fallback) for this cycle; views valid until the next step.

        ``fallback`` is the trust region's 1 - alpha in lmpc mode (0: the emulator's torque, 1: the
        law's), and 0 in fb mode (no trust region is involved).
        """
        tau, tau_fb, nxt = self.bundle.step(q, qd, q_d, qd_d, qdd_d, self.state)
        self._next[:] = nxt
        if self.mode == "fb":  # the supervisor saturates it, as it does every candidate
            return tau_fb, tau_fb, 0.0
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
