"""CiA 402 statusword decoding and the transition table, both directions."""

import pytest

from drivers.cia402.state_machine import (
    STATUS_BITS,
    TRANSITIONS,
    State,
    apply_controlword,
    decode_statusword,
    decode_statusword_fast,
    next_controlword,
)


@pytest.mark.parametrize(
    ("statusword", "state"),
    [
        (0x0250, State.SWITCH_ON_DISABLED),
        (0x0231, State.READY_TO_SWITCH_ON),
        (0x0233, State.SWITCHED_ON),
        (0x1237, State.OPERATION_ENABLED),
        (0x0217, State.QUICK_STOP_ACTIVE),
        (0x021F, State.FAULT_REACTION_ACTIVE),
        (0x0218, State.FAULT),
        (0x0000, State.NOT_READY_TO_SWITCH_ON),
        (0x0041 | 0x0020, State.UNKNOWN),  # SOD bit with ready bit: no such state
    ],
)
def test_decode_statusword(statusword: int, state: State) -> None:
    assert decode_statusword(statusword) is state
    assert decode_statusword_fast(statusword) is state


def test_fast_decoder_agrees_everywhere() -> None:
    for statusword in range(0, 0x10000, 7):
        assert decode_statusword_fast(statusword) is decode_statusword(statusword)


def test_status_bits_round_trip() -> None:
    for state, bits in STATUS_BITS.items():
        assert decode_statusword(bits) is state


def test_every_table_transition_is_what_the_drive_does() -> None:
    """The master's table and the drive's interpretation are the same state machine."""
    for (start, end), controlword in TRANSITIONS.items():
        option = 6 if (start, end) == (State.QUICK_STOP_ACTIVE, State.OPERATION_ENABLED) else 2
        assert apply_controlword(start, controlword, 0x0000, option) is end, (start, end)


def test_walk_to_operation_enabled_from_fault() -> None:
    state, previous, steps = State.FAULT, 0x0000, 0
    while (cw := next_controlword(state, State.OPERATION_ENABLED)) is not None:
        state, previous = apply_controlword(state, cw, previous, 2), cw
        steps += 1
        assert steps < 10
    assert state is State.OPERATION_ENABLED
    assert steps == 4  # fault reset, shutdown, switch on, enable operation


def test_fault_reset_needs_a_rising_edge() -> None:
    assert apply_controlword(State.FAULT, 0x0080, 0x0080, 2) is State.FAULT
    assert apply_controlword(State.FAULT, 0x0080, 0x0000, 2) is State.SWITCH_ON_DISABLED
    assert apply_controlword(State.FAULT, 0x000F, 0x0000, 2) is State.FAULT


def test_quick_stop_option_decides_where_quick_stop_ends() -> None:
    qs = apply_controlword(State.OPERATION_ENABLED, 0x0002, 0x000F, 2)
    assert qs is State.QUICK_STOP_ACTIVE
    assert apply_controlword(qs, 0x0002, 0x0002, 2) is State.SWITCH_ON_DISABLED
    assert apply_controlword(qs, 0x0002, 0x0002, 6) is State.QUICK_STOP_ACTIVE
    assert apply_controlword(qs, 0x000F, 0x0002, 6) is State.OPERATION_ENABLED


def test_no_path_raises() -> None:
    with pytest.raises(ValueError):
        next_controlword(State.FAULT_REACTION_ACTIVE, State.OPERATION_ENABLED)
