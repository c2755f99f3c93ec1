"""The runtime's lifecycle, after ros2_control's hardware components::

    UNCONFIGURED ─configure─▶ INACTIVE ─activate─▶ ACTIVE ─deactivate─▶ INACTIVE
                                 ▲                  │
                                 └──── reset ── FAULT ◀─fault─ (ACTIVE, INACTIVE)
    any state but FINALIZED ─shutdown─▶ FINALIZED

- UNCONFIGURED: config read; nothing opened.
- INACTIVE: bus connected, drives configured and readable, no torque; policy loaded and warm.
- ACTIVE: drives in Operation Enabled, the loop commands torque every period.
- FAULT: drives quick-stopped; the daemon stays up and reports why until an explicit reset.
- FINALIZED: drives disabled, bus closed; terminal.

The transition table is data; an illegal transition raises :class:`LifecycleError`. Listeners
(telemetry status, sd_notify STATUS, logs) are called after every change on the caller's thread.
"""

from __future__ import annotations

import enum
from collections.abc import Callable


class LifecycleState(str, enum.Enum):
    UNCONFIGURED = "UNCONFIGURED"
    INACTIVE = "INACTIVE"
    ACTIVE = "ACTIVE"
    FAULT = "FAULT"
    FINALIZED = "FINALIZED"


class Transition(str, enum.Enum):
    CONFIGURE = "configure"
    ACTIVATE = "activate"
    DEACTIVATE = "deactivate"
    FAULT = "fault"
    RESET = "reset"
    SHUTDOWN = "shutdown"


S, T = LifecycleState, Transition
TRANSITIONS: dict[tuple[LifecycleState, Transition], LifecycleState] = {
    (S.UNCONFIGURED, T.CONFIGURE): S.INACTIVE,
    (S.INACTIVE, T.ACTIVATE): S.ACTIVE,
    (S.ACTIVE, T.DEACTIVATE): S.INACTIVE,
    (S.ACTIVE, T.FAULT): S.FAULT,
    (S.INACTIVE, T.FAULT): S.FAULT,  # activation failed, or the bus failed while idle
    (S.FAULT, T.FAULT): S.FAULT,  # a second fault while stopped: the latest reason is kept
    (S.FAULT, T.RESET): S.INACTIVE,
    (S.UNCONFIGURED, T.SHUTDOWN): S.FINALIZED,
    (S.INACTIVE, T.SHUTDOWN): S.FINALIZED,
    (S.ACTIVE, T.SHUTDOWN): S.FINALIZED,
    (S.FAULT, T.SHUTDOWN): S.FINALIZED,
}
del S, T

Listener = Callable[[LifecycleState, "str | None"], None]


class LifecycleError(RuntimeError):
    """A transition the lifecycle does not allow from its current state."""


class Lifecycle:
    """Current state + fault reason; changed by :meth:`apply` on the loop's thread only."""

    def __init__(self) -> None:
        self.state = LifecycleState.UNCONFIGURED
        self.fault: str | None = None
        self._listeners: list[Listener] = []

    def subscribe(self, listener: Listener) -> None:
        self._listeners.append(listener)

    def can(self, transition: Transition) -> bool:
        return (self.state, transition) in TRANSITIONS

    def apply(self, transition: Transition, reason: str | None = None) -> LifecycleState:
        """Take ``transition``; ``reason`` is the fault text (kept until a reset clears it)."""
        target = TRANSITIONS.get((self.state, transition))
        if target is None:
            raise LifecycleError(f"cannot {transition.value} from {self.state.value}")
        self.state = target
        if transition is Transition.FAULT:
            self.fault = reason or "unspecified fault"
        elif transition is Transition.RESET:
            self.fault = None
        for listener in self._listeners:
            listener(self.state, self.fault)
        return target
