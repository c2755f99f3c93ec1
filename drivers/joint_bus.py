"""The ``JointBus`` protocol: what the runtime's loop needs from a set of joint drives.

The loop depends on this protocol only, never on CANopen: :class:`drivers.drive_bus.DriveBus`
implements it on CiA 402 drives; unit tests implement it with a fake (ros2_control's hardware
interface and LeRobot's motor bus play the same role). Arrays are in the config's joint order.

    bus.connect()                       # transport up, drives booted and configured (no torque)
    fb = bus.enable(hold_torque_nm)     # drives to Operation Enabled, holding that torque
    fb = bus.exchange(torque_nm)        # one control cycle: set-points out, feedback in
    bus.quick_stop(); bus.disable(); bus.close()

``exchange`` raises a :class:`drivers.errors.DriveError` subclass on a fault it detects (feedback
timeout, heartbeat lost, EMCY / drive fault, transport failure) after quick-stopping the drives.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from drivers.cia402.state_machine import State


@runtime_checkable
class JointReadings(Protocol):
    """What a drive measures per joint (a plant's ``JointState`` and ``DriveFeedback`` satisfy it)."""

    @property
    def position_rad(self) -> np.ndarray: ...

    @property
    def velocity_rad_s(self) -> np.ndarray: ...

    @property
    def torque_nm(self) -> np.ndarray: ...


@runtime_checkable
class JointFeedback(JointReadings, Protocol):
    """One cycle's feedback (``DriveFeedback`` satisfies it)."""

    @property
    def cycle(self) -> int: ...

    @property
    def commanded_torque_nm(self) -> np.ndarray: ...

    @property
    def fresh(self) -> np.ndarray: ...

    @property
    def states(self) -> tuple[State, ...]: ...


@runtime_checkable
class JointBus(Protocol):
    """A set of N joint drives run in cyclic synchronous torque, one caller thread."""

    @property
    def n_joints(self) -> int: ...

    @property
    def enabled(self) -> bool: ...

    @property
    def counters(self) -> object: ...  # a frozen dataclass of integer counters (BusCounters)

    def connect(self) -> None: ...

    def enable(self, hold_torque_nm: np.ndarray | None = None) -> JointFeedback: ...

    def exchange(self, torque_nm: np.ndarray) -> JointFeedback: ...

    def quick_stop(self) -> tuple[State, ...]: ...

    def disable(self) -> tuple[State, ...]: ...

    def fault_reset(self) -> None: ...

    def close(self) -> None: ...
