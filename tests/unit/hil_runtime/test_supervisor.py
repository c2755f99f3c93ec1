"""The supervisor's rules, table by table (hil_runtime/supervisor.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.errors import (
    DriveCommandError,
    DriveFaultError,
    DriveStateError,
    FeedbackTimeoutError,
    HeartbeatLostError,
    TransportError,
)
from hil_runtime.supervisor import (
    Fault,
    FaultKind,
    SafetyLimits,
    Supervisor,
    classify_bus_error,
)

NAN, INF = math.nan, math.inf
LIMITS = SafetyLimits(
    position_lower_rad=np.array([-1.0, -2.0]),
    position_upper_rad=np.array([1.0, 0.5]),
    velocity_limit_rad_s=np.array([2.0, 3.0]),
    torque_limit_nm=np.array([10.0, 5.0]),
    max_stale_cycles=1,
)
FRESH = np.array([True, True])


def _sup() -> Supervisor:
    return Supervisor(LIMITS, ("j1", "j2"))


@pytest.mark.parametrize(
    ("q", "qd", "expected"),
    [
        ((0.0, 0.0), (0.0, 0.0), None),
        ((1.0, -2.0), (2.0, -3.0), None),  # on the limits is inside
        ((1.0001, 0.0), (0.0, 0.0), FaultKind.POSITION_LIMIT),
        ((0.0, -2.01), (0.0, 0.0), FaultKind.POSITION_LIMIT),
        ((0.0, 0.6), (0.0, 0.0), FaultKind.POSITION_LIMIT),  # asymmetric upper limit
        ((0.0, 0.0), (-2.1, 0.0), FaultKind.VELOCITY_LIMIT),
        ((0.0, 0.0), (0.0, 3.5), FaultKind.VELOCITY_LIMIT),
        ((NAN, 0.0), (0.0, 0.0), FaultKind.FEEDBACK_NONFINITE),
        ((0.0, 0.0), (0.0, INF), FaultKind.FEEDBACK_NONFINITE),
        ((0.0, 5.0), (NAN, 0.0), FaultKind.FEEDBACK_NONFINITE),  # non-finite named before limits
    ],
)
def test_feedback_rules(q: tuple, qd: tuple, expected: FaultKind | None) -> None:
    fault = _sup().check_feedback(np.array(q), np.array(qd), FRESH)
    assert (None if fault is None else fault.kind) == expected
    if fault is not None:
        assert expected is not None
        assert "\n" not in str(fault) and str(fault).startswith(expected.value)


@pytest.mark.parametrize(
    ("fresh_sequence", "fault_at"),
    [
        ([(True, True)] * 5, None),
        ([(True, False), (True, True), (False, True), (True, True)], None),  # isolated stale cycles
        ([(True, False), (True, False)], 1),  # two in a row with max_stale_cycles = 1: FAULT at the 2nd
        ([(True, True), (False, False), (False, True)], 2),
    ],
)
def test_stale_feedback_faults_within_two_cycles(fresh_sequence: list, fault_at: int | None) -> None:
    sup = _sup()
    got = None
    for k, fresh in enumerate(fresh_sequence):
        fault = sup.check_feedback(np.zeros(2), np.zeros(2), np.array(fresh))
        if fault is not None:
            assert fault.kind is FaultKind.STALE_FEEDBACK
            got = k
            break
    assert got == fault_at
    assert sup.stale_cycles == sum(
        1 for f in fresh_sequence[: (got if got is not None else len(fresh_sequence)) + 1] if not all(f)
    )


@pytest.mark.parametrize(
    ("tau", "tau_fb", "fallback", "command", "fault", "counts"),
    [
        # tau finite: applied (clipped); counters: (law_substitutions, saturated, fallback, full_fallback)
        ((1.0, -2.0), (0.0, 0.0), 0.0, (1.0, -2.0), None, (0, 0, 0, 0)),
        ((20.0, -2.0), (0.0, 0.0), 0.0, (10.0, -2.0), None, (0, 1, 0, 0)),  # clipped: saturated
        ((10.0, -5.0), (0.0, 0.0), 0.0, (10.0, -5.0), None, (0, 1, 0, 0)),  # at the limit: saturated
        ((1.0, 1.0), (0.0, 0.0), 0.3, (1.0, 1.0), None, (0, 0, 1, 0)),  # trust-region blend
        ((1.0, 1.0), (1.0, 1.0), 1.0, (1.0, 1.0), None, (0, 0, 1, 1)),  # full fallback to the law
        ((NAN, 1.0), (3.0, -4.0), 0.0, (3.0, -4.0), None, (1, 0, 0, 0)),  # the law's torque instead
        ((INF, 1.0), (30.0, -4.0), 0.0, (10.0, -4.0), None, (1, 1, 0, 0)),
        ((NAN, 1.0), (NAN, 0.0), 0.0, None, FaultKind.POLICY_NONFINITE, (0, 0, 0, 0)),
        ((1.0, 1.0), (NAN, NAN), 0.0, (1.0, 1.0), None, (0, 0, 0, 0)),  # law NaN, policy fine: policy
        ((1.0, 1.0), (0.0, 0.0), NAN, (1.0, 1.0), None, (0, 0, 0, 0)),
    ],
)
def test_torque_rules(
    tau: tuple, tau_fb: tuple, fallback: float, command: tuple | None, fault: FaultKind | None, counts: tuple
) -> None:
    sup = _sup()
    out = np.full(2, 99.0)
    got = sup.select_torque(np.array(tau), np.array(tau_fb), fallback, out)
    assert (None if got is None else got.kind) == fault
    if command is not None:
        np.testing.assert_array_equal(out, command)
    c = sup.counters()
    assert (c["law_substitutions"], c["saturated_cycles"], c["fallback_cycles"], c["full_fallback_cycles"]) == counts


@pytest.mark.parametrize(
    ("tau", "tau_fb", "state", "command", "fault"),
    [
        ((1.0, 1.0), (0.0, 0.0), (0.5, 2.0), (1.0, 1.0), None),
        ((1.0, 1.0), (0.0, 0.0), (0.5, NAN), None, FaultKind.POLICY_NONFINITE),  # torques fine, law broken
        ((NAN, 1.0), (3.0, -4.0), (INF, 0.0), None, FaultKind.POLICY_NONFINITE),  # no law to fall back on
        ((NAN, 1.0), (3.0, -4.0), (0.5, 2.0), (3.0, -4.0), None),
    ],
)
def test_the_laws_next_state_must_be_finite(
    tau: tuple, tau_fb: tuple, state: tuple, command: tuple | None, fault: FaultKind | None
) -> None:
    sup = _sup()
    out = np.full(2, 99.0)
    got = sup.select_torque(np.array(tau), np.array(tau_fb), 0.0, out, np.array(state))
    assert (None if got is None else got.kind) == fault
    if command is not None:
        np.testing.assert_array_equal(out, command)


@pytest.mark.parametrize(
    ("error", "kind"),
    [
        (FeedbackTimeoutError((3,), 2), FaultKind.FEEDBACK_TIMEOUT),
        (HeartbeatLostError(5, "no heartbeat for 0.300 s"), FaultKind.HEARTBEAT_LOST),
        (DriveFaultError(4, 0x2310, "EMCY"), FaultKind.DRIVE_FAULT),
        (DriveStateError("drive 2 left operation enabled"), FaultKind.DRIVE_STATE),
        (TransportError("receiving failed"), FaultKind.TRANSPORT),
        (DriveCommandError("non-finite"), FaultKind.COMMAND),
        (RuntimeError("bug"), FaultKind.INTERNAL),
    ],
)
def test_bus_errors_become_faults_of_their_kind(error: Exception, kind: FaultKind) -> None:
    fault = classify_bus_error(error)
    assert isinstance(fault, Fault) and fault.kind is kind
    assert str(error) in str(fault)


def test_limits_are_checked_at_construction() -> None:
    with pytest.raises(ValueError):
        SafetyLimits(np.zeros(2), np.zeros(2), np.ones(2), np.ones(2))
    with pytest.raises(ValueError):
        SafetyLimits(-np.ones(2), np.ones(3), np.ones(2), np.ones(2))


def test_a_healthy_cycle_allocates_nothing() -> None:
    import tracemalloc

    sup = _sup()
    q, qd, fresh, tau, out = np.zeros(2), np.zeros(2), FRESH, np.ones(2), np.zeros(2)
    for _ in range(10):
        sup.check_feedback(q, qd, fresh)
        sup.select_torque(tau, tau, 0.0, out)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for _ in range(1000):
        sup.check_feedback(q, qd, fresh)
        sup.select_torque(tau, tau, 0.0, out)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = sum(stat.size_diff for stat in after.compare_to(before, "filename") if "supervisor" in str(stat.traceback))
    assert grown < 1024
