"""FakeJointBus (drivers.testing) and the check_joint_bus conformance checker (drivers.checks)."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.checks import JointBusCheckError, check_joint_bus
from drivers.cia402.state_machine import State
from drivers.errors import DriveCommandError, DriveFaultError, DriveStateError, FeedbackTimeoutError, HeartbeatLostError
from drivers.feedback import BusCounters, DriveFeedback
from drivers.joint_bus import JointBus
from drivers.testing import FakeJointBus


def test_fake_bus_passes_the_checker() -> None:
    bus = FakeJointBus(n_joints=3)
    check_joint_bus(bus, hold_torque_nm=np.array([0.1, -0.2, 0.0]))
    assert bus.events[:2] == ["connect", "enable"]
    assert bus.quick_stop_calls == 1 and bus.disable_calls == 1 and bus.close_calls == 2


def test_fake_bus_is_a_joint_bus_and_returns_drive_types() -> None:
    bus: JointBus = FakeJointBus(n_joints=2)
    bus.connect()
    feedback = bus.enable()
    assert isinstance(feedback, DriveFeedback)
    assert isinstance(bus.counters, BusCounters)


def test_double_integrator_plant_and_clipping() -> None:
    bus = FakeJointBus(n_joints=2, period_s=0.01, inertia_kgm2=[1.0, 2.0], max_torque_nm=5.0)
    bus.connect()
    bus.enable()
    feedback = bus.exchange(np.array([1.0, 10.0]))
    np.testing.assert_allclose(feedback.commanded_torque_nm, [1.0, 5.0])
    np.testing.assert_allclose(feedback.velocity_rad_s, [0.01, 0.025])
    np.testing.assert_allclose(feedback.position_rad, [1e-4, 2.5e-4])
    assert bus.commands[-1].tolist() == [1.0, 5.0]


def test_callable_plant_and_initial_position() -> None:
    def plant(q, dq, tau, dt):  # first-order: dq = tau
        return q + tau * dt, tau.copy()

    bus = FakeJointBus(n_joints=1, period_s=0.5, plant=plant, initial_position_rad=[1.0])
    bus.connect()
    bus.enable()
    assert bus.exchange(np.array([2.0])).position_rad.tolist() == [2.0]


def test_injected_error_quick_stops_then_raises() -> None:
    bus = FakeJointBus(n_joints=2)
    bus.connect()
    bus.enable()
    bus.fail_next_exchange(HeartbeatLostError(2, "no heartbeat for 0.300 s"))
    with pytest.raises(HeartbeatLostError):
        bus.exchange(np.zeros(2))
    assert not bus.enabled and bus.fail_safe_count == 1
    assert bus.states == (State.QUICK_STOP_ACTIVE, State.QUICK_STOP_ACTIVE)
    with pytest.raises(DriveStateError):
        bus.exchange(np.zeros(2))


def test_injected_drive_fault_needs_fault_reset() -> None:
    bus = FakeJointBus(n_joints=2, node_ids=[11, 12])
    bus.connect()
    bus.enable()
    bus.fail_next_exchange(DriveFaultError(12, 0x2310))
    with pytest.raises(DriveFaultError):
        bus.exchange(np.zeros(2))
    assert bus.states[1] is State.FAULT
    with pytest.raises(DriveFaultError):
        bus.enable()
    bus.fault_reset()
    assert bus.enable().states == (State.OPERATION_ENABLED,) * 2


def test_stale_feedback_then_timeout() -> None:
    bus = FakeJointBus(n_joints=3, max_missed_cycles=1)
    bus.connect()
    bus.enable()
    first = bus.exchange(np.ones(3))
    bus.make_stale([1], cycles=2)
    stale = bus.exchange(np.ones(3))
    assert stale.fresh.tolist() == [True, False, True]
    assert stale.position_rad[1] == first.position_rad[1]  # an older cycle's value
    assert stale.position_rad[0] > first.position_rad[0]
    with pytest.raises(FeedbackTimeoutError) as info:
        bus.exchange(np.ones(3))
    assert info.value.node_ids == (2,)
    assert bus.counters.dropped == 2 and not bus.enabled


def test_quick_stop_freezes_the_plant() -> None:
    bus = FakeJointBus(n_joints=1)
    bus.connect()
    bus.enable()
    bus.exchange(np.array([1.0]))
    bus.quick_stop()
    bus.enable()
    assert bus.velocity_rad_s.tolist() == [0.0]


class _AcceptsNaN(FakeJointBus):
    def _checked_setpoint(self, torque_nm: np.ndarray, name: str) -> np.ndarray:
        torque = np.asarray(torque_nm, dtype=np.float64)
        if torque.shape != (self.n_joints,):
            raise DriveCommandError("shape")
        return torque


class _StaysEnabled(FakeJointBus):
    def quick_stop(self) -> tuple[State, ...]:
        return tuple(self.states)


@pytest.mark.parametrize(
    ("bus", "message"),
    [
        (_AcceptsNaN(n_joints=2), "exchange(NaN) was accepted"),
        (_StaysEnabled(n_joints=2), "enabled is true after quick_stop()"),
    ],
)
def test_checker_names_the_broken_promise(bus: FakeJointBus, message: str) -> None:
    with pytest.raises(JointBusCheckError, match=message.replace("(", r"\(").replace(")", r"\)")):
        check_joint_bus(bus)
    assert bus.close_calls >= 1  # closed also when the check fails
