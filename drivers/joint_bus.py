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
:class:`JointBusBase` keeps that promise once for every implementation around one hook.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from drivers.cia402.state_machine import State
from drivers.errors import (
    FATAL_ERRORS,
    DriveCommandError,
    DriveFaultError,
    DriveStateError,
    FeedbackTimeoutError,
)
from drivers.feedback import DriveFeedback


def all_finite(values: list[float]) -> bool:
    """True when every float is finite: one scalar test (a NaN or an infinity makes the sum
    non-finite; so would a finite sum past 1e308: callers confirm before they refuse). On a
    handful of Python floats it is faster than one numpy call (docs/runtime.md, "One cycle")."""
    return math.isfinite(sum(values))


def clip_torque(
    torque_nm: np.ndarray, values: list[float], limit_nm: list[float], level_nm: list[float], out: np.ndarray
) -> bool:
    """``torque_nm`` (``values``: its floats, finite) clipped to ±``limit_nm`` into ``out``; True when
    some joint is at or beyond ±``level_nm`` (saturated).

    The one torque clip of the stack, used at two depths on purpose (docs/runtime.md, "One cycle"):
    the runtime's supervisor clips to its safety limit (what the law records as applied), and
    :meth:`JointBusBase.exchange` to the drives' ``max_torque_nm`` for every caller of a JointBus (the
    jog command among them), the last line of defence. A loop on Python floats: for a handful of
    joints faster than ``np.clip`` (no allocation either)."""
    out[:] = torque_nm
    saturated = False
    for i, (x, limit, level) in enumerate(zip(values, limit_nm, level_nm, strict=True)):
        if x >= level:
            saturated = True
            if x > limit:
                out[i] = limit
        elif x <= -level:
            saturated = True
            if x < -limit:
                out[i] = -limit
    return saturated


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

    def send(self, torque_nm: np.ndarray) -> None: ...

    def collect(self) -> JointFeedback: ...

    def quick_stop(self) -> tuple[State, ...]: ...

    def disable(self) -> tuple[State, ...]: ...

    def fault_reset(self) -> None: ...

    def close(self) -> None: ...


class JointBusBase(abc.ABC):
    """The shared half of every JointBus: :meth:`exchange` validates, supervises and stops safely
    around one backend hook, :meth:`_cycle_internal` (as python-can's ``BusABC.recv`` wraps
    ``_recv_internal``). :class:`drivers.drive_bus.DriveBus` and :class:`drivers.testing.FakeJointBus`
    are its two backends, so the promise of the module docstring is written once:

    - a set-point of the wrong shape or not finite raises :class:`DriveCommandError`, nothing sent;
      a finite one is clipped to each joint's ``max_torque_nm`` (:func:`clip_torque`). Defence in
      depth, on purpose: the runtime's supervisor has already replaced a non-finite policy torque
      and clipped to its safety limit (never above the drives'), so under the runtime neither
      fires; they keep the promise for every other caller (the jog command, commissioning, tests);
    - an error queued by a receiving thread or handler (:meth:`_raise_pending`) is raised by the
      exchange that follows it, checked once, after the cycle;
    - a joint without fresh feedback for more than ``max_missed_cycles`` consecutive exchanges raises
      :class:`FeedbackTimeoutError` (None: the caller supervises staleness, as the runtime's
      supervisor does with its one budget, ``safety.max_stale_cycles``); a fresh joint out of Operation Enabled raises
      :class:`DriveFaultError` (Fault) or :class:`DriveStateError`;
    - any of :data:`drivers.errors.FATAL_ERRORS` first runs :meth:`_fail_safe` (quick stop of every
      drive that answers) and leaves :attr:`enabled` false.

    The hot path allocates nothing of its own: the clipped set-point and the miss counts live in
    buffers made here once.
    """

    def __init__(
        self, node_ids: Sequence[int], max_torque_nm: Sequence[float] | np.ndarray, max_missed_cycles: int | None
    ):
        self.node_ids = tuple(node_ids)
        n = len(self.node_ids)
        self._n = n
        self.max_missed_cycles = max_missed_cycles
        self._max_torque_nm = np.broadcast_to(np.asarray(max_torque_nm, dtype=np.float64), (n,)).copy()
        self._max_torque_list = self._max_torque_nm.tolist()  # clip_torque's limits, as floats
        self._setpoint_nm = np.zeros(n)  # the clipped set-point handed to _cycle_internal
        self._missed_cycles = [0] * n  # consecutive exchanges without fresh feedback, per joint
        self._enabled = False
        self._sent = False  # an overlapped cycle's send() waits for its collect()
        self._overlapped_feedback: DriveFeedback | None = None

    # --- the backend's hooks --------------------------------------------------------------------------

    @abc.abstractmethod
    def _cycle_internal(self, setpoint_nm: np.ndarray) -> DriveFeedback:
        """Send the (validated, clipped) set-points, return this cycle's feedback. May raise any
        DriveError; a fatal one is handled by :meth:`exchange`. ``setpoint_nm`` is a buffer reused
        by the next exchange: copy what must be kept."""

    @abc.abstractmethod
    def _fail_safe(self) -> None:
        """Quick-stop every drive that still answers; never raises."""

    def _send_internal(self, setpoint_nm: np.ndarray) -> None:
        """The overlapped cycle's first half: send the set-points and the SYNC, return at once.
        By default a whole cycle now, its feedback kept for :meth:`_collect_internal` (a backend
        whose cycle does not wait on the drives, as the fake bus's)."""
        self._overlapped_feedback = self._cycle_internal(setpoint_nm)

    def _collect_internal(self) -> DriveFeedback:
        """The second half: the feedback of the SYNC :meth:`_send_internal` sent."""
        feedback = self._overlapped_feedback
        assert feedback is not None  # collect() checks that a send came first
        return feedback

    def _raise_pending(self) -> None:  # noqa: B027 - optional hook: a backend without threads has none
        """Raise an error a background thread found since the last call (none by default)."""

    # --- the shared work ------------------------------------------------------------------------------

    @property
    def n_joints(self) -> int:
        return self._n

    @property
    def enabled(self) -> bool:
        return self._enabled

    def exchange(self, torque_nm: np.ndarray) -> DriveFeedback:
        """One control cycle: send the torque set-points, return this cycle's feedback (see class doc)."""
        self._require_enabled()
        if self._sent:
            raise DriveStateError("exchange() while an overlapped cycle waits for collect()")
        try:
            setpoint = self._checked_setpoint(torque_nm, "torque_nm")  # DriveCommandError: nothing sent
            feedback = self._cycle_internal(setpoint)
            # Once per exchange, after the cycle: what the cycle's own frames brought (an EMCY, a
            # heartbeat timeout found by the receive) is raised with that cycle, as is anything
            # queued while the caller was idle.
            self._raise_pending()
            self._supervise(feedback)
        except FATAL_ERRORS:
            self._stop_for_fatal()
            raise
        return feedback

    def send(self, torque_nm: np.ndarray) -> None:
        """The overlapped cycle, first half: the torque set-points and the SYNC out, returning at
        once; :meth:`collect` returns that SYNC's feedback. The checks and the fail-safe of
        :meth:`exchange` apply to both halves. A real master's sequence (read the inputs, compute,
        write the outputs), so the drives' answer time is not in the caller's cycle."""
        self._require_enabled()
        if self._sent:
            raise DriveStateError("send() twice without collect(): one SYNC at a time")
        try:
            setpoint = self._checked_setpoint(torque_nm, "torque_nm")  # DriveCommandError: nothing sent
            self._send_internal(setpoint)
            self._sent = True
        except FATAL_ERRORS:
            self._stop_for_fatal()
            raise

    def collect(self) -> DriveFeedback:
        """The overlapped cycle, second half: the feedback of the SYNC the last :meth:`send` sent
        (what is not in by now, after a short grace, is not fresh); checked as :meth:`exchange`'s."""
        if not self._sent:
            raise DriveStateError("collect() without a send()")
        self._sent = False
        try:
            feedback = self._collect_internal()
            self._raise_pending()
            self._supervise(feedback)
        except FATAL_ERRORS:
            self._stop_for_fatal()
            raise
        return feedback

    def _require_enabled(self) -> None:
        """DriveStateError unless enabled (a pending error from a receiving thread first)."""
        if not self._enabled:
            self._raise_pending()
            raise DriveStateError("drives are not enabled: call enable() first")

    def _stop_for_fatal(self) -> None:
        """A fatal error in a cycle (:data:`drivers.errors.FATAL_ERRORS`): quick stop, not enabled."""
        self._enabled = False
        self._fail_safe()

    def _checked_setpoint(self, torque_nm: np.ndarray, name: str) -> np.ndarray:
        """``torque_nm`` clipped to the joints' limits, in the set-point buffer; refuses bad input."""
        torque = torque_nm if type(torque_nm) is np.ndarray else np.asarray(torque_nm, dtype=np.float64)
        if torque.shape != (self._n,):
            raise DriveCommandError(f"{name} has shape {torque.shape}, expected ({self._n},)")
        values = torque.tolist()
        if not all_finite(values):  # a finite sum past 1e308 is no refusal: clipped below
            bad = [self.node_ids[i] for i in np.flatnonzero(~np.isfinite(torque))]
            if bad:
                raise DriveCommandError(f"non-finite torque set-point for drive(s) {bad}")
        limit = self._max_torque_list
        clip_torque(torque, values, limit, limit, self._setpoint_nm)
        return self._setpoint_nm

    def _supervise(self, feedback: DriveFeedback) -> None:
        """The missed-cycle budget and the drives' states (see class doc)."""
        missed = self._missed_cycles
        budget = self.max_missed_cycles
        timed_out: list[int] | None = None
        for i, (fresh, state) in enumerate(zip(feedback.fresh.tolist(), feedback.states, strict=True)):
            if fresh:
                missed[i] = 0
                if state is not State.OPERATION_ENABLED:
                    self._raise_for_state(i, state)
            else:
                missed[i] += 1
                if budget is not None and missed[i] > budget:
                    timed_out = (timed_out or []) + [self.node_ids[i]]
        if timed_out and budget is not None:
            raise FeedbackTimeoutError(tuple(timed_out), budget + 1)

    def _raise_for_state(self, joint: int, state: State) -> None:
        """A fresh drive out of Operation Enabled: Fault -> DriveFaultError, else DriveStateError."""
        node_id = self.node_ids[joint]
        if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            raise DriveFaultError(node_id, self._last_emcy_code(joint), f"statusword says {state.value}")
        raise DriveStateError(f"drive {node_id} left operation enabled: {state.value}")

    def _last_emcy_code(self, joint: int) -> int:
        """The drive's last EMCY error code (0: none known)."""
        return 0

    def _reset_supervision(self) -> None:
        """On enable: the miss counts start again, no overlapped cycle open."""
        self._missed_cycles[:] = [0] * self._n
        self._sent = False
