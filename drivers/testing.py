"""A fake :class:`~drivers.joint_bus.JointBus` for unit tests of code that drives joints.

:class:`FakeJointBus` behaves like :class:`drivers.drive_bus.DriveBus` as the loop sees it (same
:class:`~drivers.feedback.DriveFeedback` and :class:`~drivers.feedback.BusCounters`, same errors
for the same misuse, quick stop before any run-time error is raised) without CAN, threads or
time: each :meth:`~FakeJointBus.exchange` advances a plant by ``period_s``::

    bus = FakeJointBus(n_joints=6, period_s=0.001)            # double integrator, 0.01 kg·m²
    bus.connect(); fb = bus.enable(np.zeros(6))
    bus.fail_next_exchange(FeedbackTimeoutError((3,), 2))     # the next exchange raises it
    bus.make_stale([2], cycles=1)                             # joint 2 misses one cycle's TPDOs
    bus.quick_stop_calls, bus.events                          # what the code under test did

The plant is any callable ``plant(position_rad, velocity_rad_s, torque_nm, period_s) ->
(position_rad, velocity_rad_s)``; the default integrates ``torque / inertia`` (semi-implicit
Euler). Nothing here imports CAN code: a runtime unit test pulls in numpy and the drive types only.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from drivers.cia402.state_machine import State
from drivers.errors import FATAL_ERRORS, DriveError, DriveFaultError, DriveStateError
from drivers.feedback import BusCounters, DriveFeedback
from drivers.joint_bus import JointBusBase

PlantStep = Callable[[np.ndarray, np.ndarray, np.ndarray, float], tuple[np.ndarray, np.ndarray]]

__all__ = ["DoubleIntegrator", "FakeJointBus", "PlantStep"]

_FAULTED = frozenset({State.FAULT, State.FAULT_REACTION_ACTIVE})
_QUICK_STOPPABLE = frozenset({State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE})


@dataclass(frozen=True)
class DoubleIntegrator:
    """q̈ = τ / J per joint (no gravity, no friction), semi-implicit Euler over one period."""

    inertia_kgm2: np.ndarray

    def __call__(
        self, position_rad: np.ndarray, velocity_rad_s: np.ndarray, torque_nm: np.ndarray, period_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        velocity = velocity_rad_s + torque_nm / self.inertia_kgm2 * period_s
        return position_rad + velocity * period_s, velocity


class FakeJointBus(JointBusBase):
    """N joints on a simulated plant, a :class:`drivers.joint_bus.JointBusBase` backend.

    ``max_torque_nm`` clips set-points as the drives do (``commanded_torque_nm`` is what the plant
    got); ``max_missed_cycles`` is the stale-feedback budget, as in ``DriveBusConfig``. Quick stop
    and disable zero the torque and freeze the plant (the brake holds). ``keep_commands=False``
    stops :attr:`commands` and the "exchange" entries of :attr:`events` growing (benchmarks and
    allocation tests run thousands of cycles).
    """

    def __init__(
        self,
        n_joints: int = 6,
        *,
        period_s: float = 0.001,
        plant: PlantStep | None = None,
        inertia_kgm2: float | Sequence[float] = 0.01,
        max_torque_nm: float | Sequence[float] = 100.0,
        initial_position_rad: Sequence[float] | np.ndarray | None = None,
        max_missed_cycles: int = 1,
        node_ids: Sequence[int] | None = None,
        keep_commands: bool = True,
    ) -> None:
        if n_joints < 1:
            raise ValueError("n_joints must be at least 1")
        ids = tuple(node_ids) if node_ids is not None else tuple(range(1, n_joints + 1))
        if len(ids) != n_joints:
            raise ValueError("node_ids must name one node per joint")
        super().__init__(ids, np.asarray(max_torque_nm, dtype=np.float64), max_missed_cycles)
        self.period_s = period_s
        self.plant: PlantStep = plant or DoubleIntegrator(
            np.broadcast_to(np.asarray(inertia_kgm2, dtype=np.float64), (n_joints,)).copy()
        )
        self.max_torque_nm = self._max_torque_nm
        self.keep_commands = keep_commands
        self.position_rad = (
            np.zeros(n_joints)
            if initial_position_rad is None
            else np.asarray(initial_position_rad, dtype=np.float64).copy()
        )
        self.velocity_rad_s = np.zeros(n_joints)
        self.applied_torque_nm = np.zeros(n_joints)

        # Records of what the code under test did.
        self.events: list[str] = []  # "connect", "enable", "exchange", "fail_safe", "quick_stop", ...
        self.commands: list[np.ndarray] = []  # commanded torque of every exchange, in order
        self.quick_stop_calls = 0
        self.disable_calls = 0
        self.fail_safe_count = 0  # quick stops the bus did itself before raising a run-time error
        self.close_calls = 0

        self._states: list[State] = [State.NOT_READY_TO_SWITCH_ON] * n_joints
        self._connected = False
        self._cycle = 0
        self._dropped = 0
        self._next_error: DriveError | None = None
        self._stale_cycles = np.zeros(n_joints, dtype=np.int64)  # cycles each joint still misses
        self._last_position = self.position_rad.copy()
        self._last_velocity = self.velocity_rad_s.copy()
        self._last_torque = np.zeros(n_joints)
        self._rx_time = np.zeros(n_joints)

    # --- fault injection -----------------------------------------------------------------------

    def fail_next_exchange(self, error: DriveError) -> None:
        """The next :meth:`exchange` quick-stops the joints and raises ``error`` (as DriveBus does).

        A :class:`DriveFaultError` also leaves its drive in Fault until :meth:`fault_reset`.
        """
        self._next_error = error

    def make_stale(self, joints: Iterable[int], cycles: int = 1) -> None:
        """Joints (indices) return no fresh feedback for the next ``cycles`` exchanges; more than
        ``max_missed_cycles`` in a row raise :class:`FeedbackTimeoutError`, as DriveBus does."""
        for j in joints:
            self._stale_cycles[j] = cycles

    # --- JointBus -------------------------------------------------------------------------------

    @property
    def states(self) -> tuple[State, ...]:
        return tuple(self._states)

    @property
    def counters(self) -> BusCounters:
        return BusCounters(
            cycles=self._cycle,
            frames_sent=self._cycle * (self._n + 1),
            frames_received=self._cycle * self._n - self._dropped,
            dropped=self._dropped,
        )

    def connect(self) -> None:
        self.events.append("connect")
        if not self._connected:
            self._connected = True
            self._states = [State.SWITCH_ON_DISABLED] * self._n

    def enable(self, hold_torque_nm: np.ndarray | None = None) -> DriveFeedback:
        self.events.append("enable")
        if not self._connected:
            raise DriveStateError("not connected: call connect() first")
        for i, state in enumerate(self._states):
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                raise DriveFaultError(self.node_ids[i], 0, "in Fault: call fault_reset() first")
        torque = (
            np.zeros(self._n)
            if hold_torque_nm is None
            else self._checked_setpoint(hold_torque_nm, "hold_torque_nm").copy()
        )
        self._states = [State.OPERATION_ENABLED] * self._n
        self._reset_supervision()
        self._enabled = True
        return self._step(torque)

    def _cycle_internal(self, setpoint_nm: np.ndarray) -> DriveFeedback:
        if self.keep_commands:
            self.events.append("exchange")
            self.commands.append(setpoint_nm.copy())
        if self._next_error is not None:
            error, self._next_error = self._next_error, None
            if isinstance(error, DriveFaultError) and error.node_id in self.node_ids:
                self._states[self.node_ids.index(error.node_id)] = State.FAULT
            if not isinstance(error, FATAL_ERRORS):  # the base stops safely for the fatal ones
                self._fail_safe()
            raise error
        return self._step(setpoint_nm)

    def quick_stop(self) -> tuple[State, ...]:
        self.events.append("quick_stop")
        self.quick_stop_calls += 1
        return self._stop(State.QUICK_STOP_ACTIVE)

    def disable(self) -> tuple[State, ...]:
        self.events.append("disable")
        self.disable_calls += 1
        return self._stop(State.SWITCH_ON_DISABLED)

    def fault_reset(self) -> None:
        self.events.append("fault_reset")
        if not self._connected:
            raise DriveStateError("not connected: call connect() first")
        self._next_error = None
        self._states = [
            State.SWITCH_ON_DISABLED if s in (State.FAULT, State.FAULT_REACTION_ACTIVE) else s for s in self._states
        ]

    def close(self) -> None:
        self.events.append("close")
        self.close_calls += 1
        if self._enabled:
            self.disable()
        self._connected = False

    def __enter__(self) -> FakeJointBus:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- internals ------------------------------------------------------------------------------

    def _step(self, commanded: np.ndarray) -> DriveFeedback:
        self._cycle += 1
        sync_time = time.monotonic()
        moving = np.array([s is State.OPERATION_ENABLED for s in self._states])
        self.applied_torque_nm = np.where(moving, commanded, 0.0)
        position, velocity = self.plant(self.position_rad, self.velocity_rad_s, self.applied_torque_nm, self.period_s)
        self.position_rad = np.where(moving, position, self.position_rad)
        self.velocity_rad_s = np.where(moving, velocity, 0.0)
        fresh = self._stale_cycles <= 0
        self._stale_cycles[~fresh] -= 1
        self._dropped += int((~fresh).sum())
        # A joint that misses its TPDO reports what it reported last (an older cycle's values).
        self._last_position = np.where(fresh, self.position_rad, self._last_position)
        self._last_velocity = np.where(fresh, self.velocity_rad_s, self._last_velocity)
        self._last_torque = np.where(fresh, self.applied_torque_nm, self._last_torque)
        self._rx_time = np.where(fresh, sync_time, self._rx_time)
        return DriveFeedback(
            cycle=self._cycle,
            sync_time_s=sync_time,
            position_rad=self._last_position.copy(),
            velocity_rad_s=self._last_velocity.copy(),
            torque_nm=self._last_torque.copy(),
            commanded_torque_nm=commanded.copy(),  # the set-point buffer is reused next cycle
            fresh=fresh.copy(),
            rx_time_s=self._rx_time.copy(),
            states=tuple(self._states),
        )

    def _fail_safe(self) -> None:
        self.events.append("fail_safe")
        self.fail_safe_count += 1
        self._enabled = False
        self._states = [s if s in _FAULTED else State.QUICK_STOP_ACTIVE for s in self._states]
        self.velocity_rad_s = np.zeros(self._n)
        self.applied_torque_nm = np.zeros(self._n)

    def _stop(self, target: State) -> tuple[State, ...]:
        """Quick stop: Operation Enabled -> Quick Stop Active; disable (or quick stop from any
        other state): Switch On Disabled. A faulted drive stays in Fault."""
        self._enabled = False
        if self._connected:
            self._states = [
                s
                if s in (State.FAULT, State.FAULT_REACTION_ACTIVE)
                else State.QUICK_STOP_ACTIVE
                if target is State.QUICK_STOP_ACTIVE and s in _QUICK_STOPPABLE
                else State.SWITCH_ON_DISABLED
                for s in self._states
            ]
        self.velocity_rad_s = np.zeros(self._n)
        self.applied_torque_nm = np.zeros(self._n)
        return tuple(self._states)
