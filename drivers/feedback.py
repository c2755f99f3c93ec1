"""What one control cycle returns (:class:`DriveFeedback`) and the bus counters (:class:`BusCounters`).

Shared by :class:`drivers.drive_bus.DriveBus` and :class:`drivers.testing.FakeJointBus`, so a
loop written against one gets exactly the same types from the other.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.cia402.state_machine import State


@dataclass(frozen=True, slots=True)
class DriveFeedback:
    """One control cycle's result, arrays in joint order of the config."""

    cycle: int
    sync_time_s: float  # time.monotonic() when the SYNC was sent
    position_rad: np.ndarray
    velocity_rad_s: np.ndarray
    torque_nm: np.ndarray  # measured (0x6077)
    commanded_torque_nm: np.ndarray  # what was sent: clipped to max torque, quantised to 1 ‰
    fresh: np.ndarray  # bool: this cycle's TPDOs arrived; False: values from an older cycle
    rx_time_s: np.ndarray  # time.monotonic() the drive's last TPDO was received
    states: tuple[State, ...]


@dataclass(frozen=True, slots=True)
class BusCounters:
    cycles: int = 0
    frames_sent: int = 0
    frames_received: int = 0
    dropped: int = 0  # expected TPDOs not received by the cycle's deadline
    late: int = 0  # TPDOs received after their deadline (or twice in one cycle)
    malformed: int = 0  # wrong length, impossible content, error/remote/extended frames
    unknown_cob_id: int = 0
    emcy: int = 0
    heartbeats: int = 0
