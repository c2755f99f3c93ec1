"""The CiA 402 power state machine: statusword decoding, controlword commands, transitions.

The master side uses :data:`TRANSITIONS` ({(from, to): controlword}) and :func:`next_controlword`
to walk a drive to a target state one SYNC at a time. The drive side (sim_target) uses
:func:`apply_controlword`, the same table read the other way, so both ends share one definition.
"""

from __future__ import annotations

from enum import Enum
from typing import Final


class State(Enum):
    NOT_READY_TO_SWITCH_ON = "not ready to switch on"
    SWITCH_ON_DISABLED = "switch on disabled"
    READY_TO_SWITCH_ON = "ready to switch on"
    SWITCHED_ON = "switched on"
    OPERATION_ENABLED = "operation enabled"
    QUICK_STOP_ACTIVE = "quick stop active"
    FAULT_REACTION_ACTIVE = "fault reaction active"
    FAULT = "fault"
    UNKNOWN = "unknown"  # a statusword no drive may send: counted as malformed


# Statusword bits 0..3, 5, 6 (ready, switched on, operation enabled, fault, quick stop, SOD).
# (mask, value) pairs from CiA 402 table 30; the order matters (narrower masks first).
_STATUS_PATTERNS: Final[tuple[tuple[int, int, State], ...]] = (
    (0x004F, 0x0000, State.NOT_READY_TO_SWITCH_ON),
    (0x004F, 0x0040, State.SWITCH_ON_DISABLED),
    (0x006F, 0x0021, State.READY_TO_SWITCH_ON),
    (0x006F, 0x0023, State.SWITCHED_ON),
    (0x006F, 0x0027, State.OPERATION_ENABLED),
    (0x006F, 0x0007, State.QUICK_STOP_ACTIVE),
    (0x004F, 0x000F, State.FAULT_REACTION_ACTIVE),
    (0x004F, 0x0008, State.FAULT),
)

# Statusword of each state as the emulated drive reports it.
STATUS_BITS: Final[dict[State, int]] = {
    State.NOT_READY_TO_SWITCH_ON: 0x0000,
    State.SWITCH_ON_DISABLED: 0x0040,
    State.READY_TO_SWITCH_ON: 0x0021,
    State.SWITCHED_ON: 0x0023,
    State.OPERATION_ENABLED: 0x0027,
    State.QUICK_STOP_ACTIVE: 0x0007,
    State.FAULT_REACTION_ACTIVE: 0x000F,
    State.FAULT: 0x0008,
}

SW_VOLTAGE_ENABLED: Final = 0x0010
SW_WARNING: Final = 0x0080
SW_REMOTE: Final = 0x0200
SW_TARGET_REACHED: Final = 0x0400
SW_INTERNAL_LIMIT: Final = 0x0800  # set while the target torque is clipped to 0x6072
SW_FOLLOWS_COMMAND: Final = 0x1000  # cyclic modes: the drive follows the command value


def decode_statusword(statusword: int) -> State:
    for mask, value, state in _STATUS_PATTERNS:
        if statusword & mask == value:
            return state
    return State.UNKNOWN


# Cache all 128 combinations of the relevant bits: the driver decodes one per drive per cycle.
_STATE_BY_BITS: Final[tuple[State, ...]] = tuple(decode_statusword((b & 0x0F) | ((b & 0x30) << 1)) for b in range(64))


def decode_statusword_fast(statusword: int) -> State:
    """Same as :func:`decode_statusword`, a table lookup (hot path)."""
    return _STATE_BY_BITS[(statusword & 0x0F) | ((statusword >> 1) & 0x30)]


class Command(Enum):
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    ENABLE_OPERATION = 0x000F
    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    DISABLE_OPERATION = 0x0007
    FAULT_RESET = 0x0080


CW_FAULT_RESET: Final = 0x0080

#: {(from, to): controlword} for every transition a master commands (CiA 402 figure 42).
TRANSITIONS: Final[dict[tuple[State, State], int]] = {
    (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON): 0x0006,  # 2 shutdown
    (State.READY_TO_SWITCH_ON, State.SWITCHED_ON): 0x0007,  # 3 switch on
    (State.SWITCHED_ON, State.OPERATION_ENABLED): 0x000F,  # 4 enable operation
    (State.OPERATION_ENABLED, State.SWITCHED_ON): 0x0007,  # 5 disable operation
    (State.SWITCHED_ON, State.READY_TO_SWITCH_ON): 0x0006,  # 6 shutdown
    (State.READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED): 0x0000,  # 7 disable voltage
    (State.OPERATION_ENABLED, State.READY_TO_SWITCH_ON): 0x0006,  # 8 shutdown
    (State.OPERATION_ENABLED, State.SWITCH_ON_DISABLED): 0x0000,  # 9 disable voltage
    (State.SWITCHED_ON, State.SWITCH_ON_DISABLED): 0x0000,  # 10 disable voltage
    (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE): 0x0002,  # 11 quick stop
    (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED): 0x0000,  # 12 disable voltage
    (State.FAULT, State.SWITCH_ON_DISABLED): 0x0080,  # 15 fault reset (rising edge)
    (State.QUICK_STOP_ACTIVE, State.OPERATION_ENABLED): 0x000F,  # 16 (option codes 5..8)
}

# The path a master walks from each state towards Operation Enabled.
_TOWARDS_ENABLED: Final[dict[State, State]] = {
    State.FAULT: State.SWITCH_ON_DISABLED,
    State.SWITCH_ON_DISABLED: State.READY_TO_SWITCH_ON,
    State.READY_TO_SWITCH_ON: State.SWITCHED_ON,
    State.SWITCHED_ON: State.OPERATION_ENABLED,
    State.QUICK_STOP_ACTIVE: State.SWITCH_ON_DISABLED,
}


def next_controlword(current: State, target: State) -> int | None:
    """Controlword for the next step from ``current`` towards ``target``; None when there.

    Only Operation Enabled and Switch On Disabled are walked to over several steps; any other
    target must be one transition away. Raises ValueError when no path exists.
    """
    if current is target:
        return None
    direct = TRANSITIONS.get((current, target))
    if target is State.OPERATION_ENABLED:
        step = _TOWARDS_ENABLED.get(current)
        if step is None:
            raise ValueError(f"no path from {current.value} to {target.value}")
        return TRANSITIONS[(current, step)]
    if direct is not None:
        return direct
    if target is State.SWITCH_ON_DISABLED and current is not State.FAULT_REACTION_ACTIVE:
        return 0x0000
    raise ValueError(f"no transition from {current.value} to {target.value}")


def apply_controlword(state: State, controlword: int, previous_controlword: int, quick_stop_option: int) -> State:
    """Drive side: the state after one controlword (applied at SYNC).

    ``quick_stop_option`` is 0x605A: 5..8 stay in Quick Stop Active, anything else passes on to
    Switch On Disabled once stopped (the emulated drive stops at once: its brake holds the joint).
    Fault and Fault Reaction Active are left only by a fault reset (rising edge of bit 7).
    """
    if state is State.FAULT:
        rising_reset = controlword & CW_FAULT_RESET and not previous_controlword & CW_FAULT_RESET
        return State.SWITCH_ON_DISABLED if rising_reset else State.FAULT
    if state in (State.FAULT_REACTION_ACTIVE, State.NOT_READY_TO_SWITCH_ON, State.UNKNOWN):
        return state
    if controlword & CW_FAULT_RESET:
        return state  # bit 7 outside Fault: the other bits are ignored
    if controlword & 0x0002 == 0:  # disable voltage
        return State.SWITCH_ON_DISABLED
    if controlword & 0x0006 == 0x0002:  # quick stop (bit 2 low)
        if state is State.OPERATION_ENABLED:
            return State.QUICK_STOP_ACTIVE
        if state is State.QUICK_STOP_ACTIVE:
            return state if 5 <= quick_stop_option <= 8 else State.SWITCH_ON_DISABLED
        return State.SWITCH_ON_DISABLED
    if state is State.QUICK_STOP_ACTIVE:
        if 5 <= quick_stop_option <= 8 and controlword & 0x000F == 0x000F:
            return State.OPERATION_ENABLED
        return state if 5 <= quick_stop_option <= 8 else State.SWITCH_ON_DISABLED
    low = controlword & 0x000F
    if low in (0x0006, 0x000E):  # shutdown
        if state in (State.SWITCH_ON_DISABLED, State.SWITCHED_ON, State.OPERATION_ENABLED):
            return State.READY_TO_SWITCH_ON
        return state
    if low == 0x0007:  # switch on / disable operation
        if state in (State.READY_TO_SWITCH_ON, State.OPERATION_ENABLED):
            return State.SWITCHED_ON
        return state
    if low == 0x000F:  # enable operation (switch on + enable in one step is allowed)
        if state is State.SWITCHED_ON:
            return State.OPERATION_ENABLED
        if state is State.READY_TO_SWITCH_ON:
            return State.SWITCHED_ON
        return state
    return state
