"""``check_joint_bus``: does an implementation behave as :class:`~drivers.joint_bus.JointBus` says?

In the manner of Gymnasium's ``check_env``: run it against any implementation (DriveBus on the
emulated drives, :class:`drivers.testing.FakeJointBus`, a real drive set on a test bench) before
the runtime's loop is trusted with it. It walks the whole life cycle once::

    connect -> enable(hold) -> exchange x cycles -> refused set-points (wrong shape, NaN)
    -> quick_stop -> exchange refused -> enable again -> disable -> close (twice)

and raises :class:`JointBusCheckError` naming the first broken promise. Every set-point it sends
is ``hold_torque_nm`` (zero by default): on a real arm, pass the gravity torque at the current
position, or run it with the arm on its brakes removed from the load.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from drivers.cia402.state_machine import State
from drivers.errors import DriveCommandError, DriveError, DriveStateError
from drivers.joint_bus import JointBus, JointFeedback

__all__ = ["JointBusCheckError", "check_joint_bus", "check_feedback"]

_STOPPED = frozenset({State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED, State.FAULT, State.FAULT_REACTION_ACTIVE})
_METHODS = ("connect", "enable", "exchange", "quick_stop", "disable", "fault_reset", "close")


class JointBusCheckError(AssertionError):
    """The bus under check broke a promise of the JointBus protocol (the message says which)."""


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise JointBusCheckError(message)


def check_feedback(feedback: Any, n_joints: int, where: str) -> None:
    """One cycle's feedback: every JointFeedback field present, (n,) float arrays, finite where fresh."""
    _require(
        isinstance(feedback, JointFeedback),
        f"{where}: returned {type(feedback).__name__}, which lacks JointFeedback fields",
    )
    _require(isinstance(feedback.cycle, (int, np.integer)), f"{where}: cycle is not an integer")
    for name in ("position_rad", "velocity_rad_s", "torque_nm", "commanded_torque_nm"):
        value = getattr(feedback, name)
        _require(
            isinstance(value, np.ndarray) and value.shape == (n_joints,),
            f"{where}: {name} is not an ndarray of shape ({n_joints},)",
        )
        _require(value.dtype.kind == "f", f"{where}: {name} has dtype {value.dtype}, expected float")
    fresh = feedback.fresh
    _require(
        isinstance(fresh, np.ndarray) and fresh.shape == (n_joints,) and fresh.dtype == np.bool_,
        f"{where}: fresh is not a bool ndarray of shape ({n_joints},)",
    )
    for name in ("position_rad", "velocity_rad_s", "torque_nm"):
        _require(bool(np.isfinite(getattr(feedback, name)[fresh]).all()), f"{where}: non-finite fresh {name}")
    _require(bool(np.isfinite(feedback.commanded_torque_nm).all()), f"{where}: non-finite commanded_torque_nm")
    _require(
        isinstance(feedback.states, tuple)
        and len(feedback.states) == n_joints
        and all(isinstance(s, State) for s in feedback.states),
        f"{where}: states is not a tuple of {n_joints} State values",
    )


def _check_counters(bus: JointBus, where: str) -> dict[str, int]:
    counters = bus.counters
    _require(
        dataclasses.is_dataclass(counters) and not isinstance(counters, type),
        f"{where}: counters is not a dataclass instance",
    )
    values: dict[str, int] = dataclasses.asdict(counters)  # type: ignore[call-overload]  # checked just above
    _require(
        all(isinstance(v, int) and v >= 0 for v in values.values()),
        f"{where}: counters are not all non-negative integers: {values}",
    )
    try:
        setattr(counters, next(iter(values)), 0)
    except dataclasses.FrozenInstanceError:
        pass
    else:
        raise JointBusCheckError(f"{where}: counters is a mutable snapshot (expected a frozen dataclass)")
    return values


def _expect_refused(bus: JointBus, torque: Any, what: str) -> None:
    try:
        bus.exchange(torque)
    except DriveCommandError:
        pass
    except DriveError as exc:
        raise JointBusCheckError(f"exchange({what}) raised {type(exc).__name__}, expected DriveCommandError") from exc
    else:
        raise JointBusCheckError(f"exchange({what}) was accepted; it must raise DriveCommandError")
    _require(bus.enabled, f"exchange({what}) was refused but left the bus disabled (nothing was sent)")


def _expect_not_enabled(bus: JointBus, hold: np.ndarray, when: str) -> None:
    try:
        bus.exchange(hold)
    except DriveStateError:
        return
    raise JointBusCheckError(f"exchange() {when} was accepted; it must raise DriveStateError")


def check_joint_bus(bus: JointBus, hold_torque_nm: np.ndarray | None = None, cycles: int = 5) -> None:
    """Walk ``bus`` (not yet connected) through its life cycle; :class:`JointBusCheckError` on a
    broken promise. The bus is closed at the end, also when a check fails."""
    for name in _METHODS:
        _require(callable(getattr(bus, name, None)), f"{type(bus).__name__} has no method {name}()")
    try:
        n = bus.n_joints
        _require(isinstance(n, int) and n >= 1, f"n_joints is {n!r}, expected a positive int")
        hold = np.zeros(n) if hold_torque_nm is None else np.asarray(hold_torque_nm, dtype=np.float64)
        _require(hold.shape == (n,), f"hold_torque_nm has shape {hold.shape}, expected ({n},)")

        _require(not bus.enabled, "enabled is true before connect()")
        bus.connect()
        _require(not bus.enabled, "connect() enabled the drives (it must leave them without torque)")
        _expect_not_enabled(bus, hold, "before enable()")

        feedback = bus.enable(hold)
        check_feedback(feedback, n, "enable()")
        _require(bus.enabled, "enabled is false after enable() returned")
        _require(
            all(s is State.OPERATION_ENABLED for s in feedback.states),
            f"enable() returned states {[s.value for s in feedback.states]}, expected operation enabled",
        )
        before = _check_counters(bus, "after enable()")

        last_cycle = int(feedback.cycle)
        for k in range(cycles):
            feedback = bus.exchange(hold)
            where = f"exchange() #{k + 1}"
            check_feedback(feedback, n, where)
            _require(
                int(feedback.cycle) > last_cycle, f"{where}: cycle {feedback.cycle} did not advance from {last_cycle}"
            )
            last_cycle = int(feedback.cycle)
        after = _check_counters(bus, f"after {cycles} exchanges")
        if "cycles" in before:
            _require(
                after["cycles"] >= before["cycles"] + cycles,
                f"counters.cycles went from {before['cycles']} to {after['cycles']} over {cycles} exchanges",
            )

        _expect_refused(bus, np.zeros(n + 1), "wrong shape")
        _expect_refused(bus, np.full(n, np.nan), "NaN")

        states = bus.quick_stop()
        _require(not bus.enabled, "enabled is true after quick_stop()")
        _require(
            isinstance(states, tuple) and len(states) == n and all(s in _STOPPED for s in states),
            f"quick_stop() returned {states!r}, expected {n} quick-stop/switch-on-disabled states",
        )
        _expect_not_enabled(bus, hold, "after quick_stop()")

        feedback = bus.enable(hold)
        check_feedback(feedback, n, "enable() after quick_stop()")
        _require(bus.enabled, "enable() after quick_stop() did not enable")
        states = bus.disable()
        _require(not bus.enabled, "enabled is true after disable()")
        _require(
            isinstance(states, tuple)
            and len(states) == n
            and all(s in (State.SWITCH_ON_DISABLED, State.FAULT) for s in states),
            f"disable() returned {states!r}, expected switch on disabled",
        )
        bus.fault_reset()  # nothing faulted: must be harmless
    finally:
        bus.close()
    bus.close()  # idempotent
    _require(not bus.enabled, "enabled is true after close()")
