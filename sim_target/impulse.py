"""External joint torque impulses (the paper's disturbance), resolved to the plant's physics substeps."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TorqueImpulse:
    """An external joint torque applied over [start_s, start_s + duration_s).

    The plant resolves it to its physics substeps: a pulse shorter than a substep (or not aligned
    with one) is applied as its average over each substep it overlaps, so the impulse (N·m·s) is
    preserved exactly and its timing to one substep (period / substeps).
    """

    torque_nm: tuple[float, ...]  # one per controlled joint
    start_s: float
    duration_s: float

    def mean_torque_nm(self, t0_s: float, period_s: float) -> np.ndarray:
        overlap_s = min(t0_s + period_s, self.start_s + self.duration_s) - max(t0_s, self.start_s)
        fraction = max(overlap_s, 0.0) / period_s
        return np.asarray(self.torque_nm, dtype=float) * fraction


# The paper's disturbance (Sec. IV): [1, 1, 5, 5, 10, 10] N·m at t = 2 s. Duration not given by
# the paper; 20 µs, the same pulse as the models simulator (docs/conditions.md: a whole 1 ms of
# 10 N·m would spin the 1.25e-4 kg·m² wrist 3 to ~80 rad/s, thirty times its velocity limit).
PAPER_DISTURBANCE = TorqueImpulse(torque_nm=(1.0, 1.0, 5.0, 5.0, 10.0, 10.0), start_s=2.0, duration_s=2e-5)


def external_profile_nm(
    impulses: Sequence[TorqueImpulse], t0_s: float, period_s: float, substeps: int, n_joints: int
) -> np.ndarray | None:
    """(substeps, N) external torque per physics substep of the period starting at ``t0_s``; None
    when no impulse touches it. Each substep carries the impulse's mean over that substep: a 20 µs
    pulse at the start of a period acts in its first 31 µs substep (32 substeps), as in the models
    simulator (which integrates the pulse exactly), not spread over the whole period."""

    active = [i for i in impulses if i.start_s < t0_s + period_s and i.start_s + i.duration_s > t0_s]
    if not active:
        return None
    h_s = period_s / substeps
    profile = np.zeros((substeps, n_joints))
    for impulse in active:
        if impulse.duration_s < h_s and t0_s <= impulse.start_s + 0.5 * impulse.duration_s < t0_s + period_s:
            # Shorter than a substep: semi-implicit Euler moves a substep's whole length at the
            # velocity its force produced, so the impulse is shared between the two substeps
            # around its centroid (linear weights): the arm's displacement over the period is
            # then the exact integration's (the models simulator's) to first order.
            x = (impulse.start_s + 0.5 * impulse.duration_s - t0_s) / h_s
            k = min(int(x), substeps - 1)
            w = x - k if k + 1 < substeps else 0.0
            torque_nm = np.asarray(impulse.torque_nm, dtype=float) * impulse.duration_s / h_s
            profile[k] += (1.0 - w) * torque_nm
            if w > 0.0:
                profile[k + 1] += w * torque_nm
            continue
        for k in range(substeps):
            profile[k] += impulse.mean_torque_nm(t0_s + k * h_s, h_s)
    return profile
