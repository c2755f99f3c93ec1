"""JointBusBase: the JointBus promise written once, around one hook (drivers.joint_bus)."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.cia402.state_machine import State
from drivers.drive_bus import DriveBus
from drivers.errors import (
    FATAL_ERRORS,
    DriveCommandError,
    DriveError,
    DriveFaultError,
    DriveStateError,
    FeedbackTimeoutError,
    HeartbeatLostError,
    TransportError,
)
from drivers.feedback import DriveFeedback
from drivers.joint_bus import JointBusBase
from drivers.testing import FakeJointBus
from hil_runtime.supervisor import FaultKind, classify_bus_error


class _Scripted(JointBusBase):
    """A backend that only replays scripted (fresh, state) cycles: everything else is the base's."""

    def __init__(self, script: list[tuple[list[bool], State]], pending: DriveError | None = None) -> None:
        super().__init__([1, 2], [5.0, 5.0], max_missed_cycles=1)
        self.script = script
        self.pending = pending
        self.sent: list[list[float]] = []
        self.stops = 0
        self._enabled = True

    def _cycle_internal(self, setpoint_nm: np.ndarray) -> DriveFeedback:
        fresh, state = self.script.pop(0)
        self.sent.append(setpoint_nm.tolist())
        z = np.zeros(2)
        return DriveFeedback(0, 0.0, z, z, z, setpoint_nm.copy(), np.array(fresh), z, (state, state))

    def _fail_safe(self) -> None:
        self.stops += 1

    def _raise_pending(self) -> None:
        if self.pending is not None:
            error, self.pending = self.pending, None
            raise error


OK = ([True, True], State.OPERATION_ENABLED)


def test_set_points_are_checked_and_clipped_once_by_the_base() -> None:
    bus = _Scripted([OK, OK])
    with pytest.raises(DriveCommandError, match=r"drive\(s\) \[2\]"):
        bus.exchange(np.array([0.0, np.nan]))
    with pytest.raises(DriveCommandError, match="shape"):
        bus.exchange(np.zeros(3))
    assert bus.sent == [] and bus.enabled and bus.stops == 0  # nothing sent, nothing stopped
    assert bus.exchange(np.array([9.0, -1.0])).commanded_torque_nm.tolist() == [5.0, -1.0]


def test_missed_cycle_budget_stops_then_raises() -> None:
    stale = ([True, False], State.OPERATION_ENABLED)
    bus = _Scripted([stale, stale])
    bus.exchange(np.zeros(2))  # one miss is within max_missed_cycles = 1
    with pytest.raises(FeedbackTimeoutError, match="drive.s. 2 for 2"):
        bus.exchange(np.zeros(2))
    assert bus.stops == 1 and not bus.enabled
    with pytest.raises(DriveStateError, match="not enabled"):
        bus.exchange(np.zeros(2))


@pytest.mark.parametrize(
    ("state", "error"), [(State.FAULT, DriveFaultError), (State.SWITCH_ON_DISABLED, DriveStateError)]
)
def test_a_fresh_drive_out_of_operation_enabled_stops_the_bus(state: State, error: type[DriveError]) -> None:
    bus = _Scripted([([True, True], state)])
    with pytest.raises(error):
        bus.exchange(np.zeros(2))
    assert bus.stops == 1 and not bus.enabled


def test_a_pending_error_is_raised_with_the_cycle_that_follows_it() -> None:
    bus = _Scripted([OK], pending=HeartbeatLostError(2, "no heartbeat"))
    with pytest.raises(HeartbeatLostError):
        bus.exchange(np.zeros(2))
    assert len(bus.sent) == 1 and bus.stops == 1


def test_both_buses_share_the_base_and_every_fatal_error_has_its_fault_kind() -> None:
    assert issubclass(DriveBus, JointBusBase) and issubclass(FakeJointBus, JointBusBase)
    assert DriveBus.exchange is JointBusBase.exchange and FakeJointBus.exchange is JointBusBase.exchange
    for error_type in FATAL_ERRORS:
        assert FaultKind(error_type.fault_kind) is not FaultKind.INTERNAL
    assert classify_bus_error(TransportError("gone")).kind is FaultKind.TRANSPORT


def test_no_missed_cycle_budget_leaves_staleness_to_the_caller() -> None:
    """max_missed_cycles None (the runtime's drive bus: its supervisor has the one budget): stale
    cycles pass through, marked not fresh; the drives' states are still checked."""
    stale = ([False, False], State.OPERATION_ENABLED)
    bus = _Scripted([stale] * 5 + [([True, True], State.FAULT)])
    bus.max_missed_cycles = None
    for _ in range(5):
        assert not bus.exchange(np.zeros(2)).fresh.any()
    with pytest.raises(DriveFaultError):
        bus.exchange(np.zeros(2))
    assert bus.stops == 1
