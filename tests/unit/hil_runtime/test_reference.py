"""The reference: a quintic ramp from the measured pose onto the condition's start (no step in
position, velocity or acceleration), the condition after it, its end held; or hold."""

from __future__ import annotations

import numpy as np
import pytest

from hil_runtime.conditions import load_conditions
from hil_runtime.reference import Reference, quintic, ramp_duration_s

PERIOD_S = 0.001
Q0 = np.array([0.0, -0.5, 0.8, -0.3, 0.0, 0.0])
VMAX = np.full(6, 2.5)


def _c(name: str):
    return next(c for c in load_conditions(None) if c.name == name)


def test_quintic_meets_both_ends() -> None:
    p0, p1, v1, a1 = np.array([0.0, 1.0]), np.array([1.0, -1.0]), np.array([0.3, 0.1]), np.array([0.5, -2.0])
    q, qd, qdd = quintic(p0, p1, v1, a1, 2.0, np.array([0.0, 2.0]))
    np.testing.assert_allclose(q, [p0, p1], atol=1e-12)
    np.testing.assert_allclose(qd, np.vstack([np.zeros(2), v1]), atol=1e-12)
    np.testing.assert_allclose(qdd, np.vstack([np.zeros(2), a1]), atol=1e-12)


@pytest.mark.parametrize("name", ["C1", "C4"])
def test_ramp_then_condition_is_continuous_and_starts_at_rest_at_the_measured_pose(name: str) -> None:
    condition = _c(name)
    ref = Reference.ramp_then(Q0, condition, PERIOD_S, 2.0, VMAX, 0.25)
    assert ref.name == name and ref.ramp_cycles >= 2000
    np.testing.assert_allclose(ref.q[0], Q0)
    np.testing.assert_allclose(ref.qd[0], 0.0)
    np.testing.assert_allclose(ref.qdd[0], 0.0)
    # No step anywhere: consecutive rows differ by at most the speed times a period.
    assert np.abs(np.diff(ref.q, axis=0)).max() <= VMAX.max() * PERIOD_S
    assert np.abs(ref.qd[: ref.ramp_cycles]).max(axis=0).max() <= 0.25 * 2.5 + 1e-9
    # The seam: the condition's first row follows the ramp's last as its own rows follow each other.
    start = condition.reference(0.0)
    np.testing.assert_allclose(ref.q[ref.ramp_cycles], start[0], atol=1e-12)
    seam = np.abs(ref.qd[ref.ramp_cycles] - ref.qd[ref.ramp_cycles - 1]).max()
    assert seam < 1e-2
    # Condition rows follow its own formula; past the end, its last position at rest.
    t = 1.2345
    k = ref.ramp_cycles + round(t / PERIOD_S)
    np.testing.assert_allclose(ref.at(k)[0], condition.reference(round(t / PERIOD_S) * PERIOD_S)[0], atol=1e-12)
    q_end, qd_end, qdd_end = ref.at(ref.cycles + 10_000)
    np.testing.assert_allclose(q_end, ref.q[-1])
    assert not qd_end.any() and not qdd_end.any()


def test_a_far_start_lengthens_the_ramp_to_respect_the_speed_bound() -> None:
    p1 = Q0 + np.array([0, 0, 2.0, 0, 0, 0])
    duration = ramp_duration_s(Q0, p1, np.zeros(6), np.zeros(6), 0.5, VMAX * 0.25, PERIOD_S)
    assert duration >= 1.875 * 2.0 / (2.5 * 0.25) - 1e-9  # the quintic's peak speed
    _, qd, _ = quintic(Q0, p1, np.zeros(6), np.zeros(6), duration, np.linspace(0, duration, 1001))
    assert np.abs(qd).max() <= 2.5 * 0.25 + 1e-9


def test_hold_is_the_measured_pose_at_rest_forever() -> None:
    ref = Reference.hold(Q0)
    for k in (0, 1, 10**7):
        q, qd, qdd = ref.at(k)
        np.testing.assert_array_equal(q, Q0)
        assert not qd.any() and not qdd.any()
    assert ref.ramp_cycles == 0


def test_a_condition_for_another_arm_is_refused() -> None:
    with pytest.raises(ValueError, match="joints"):
        Reference.ramp_then(np.zeros(3), _c("C1"), PERIOD_S, 1.0, np.ones(3))
