"""CiA 402 on the drive's side: the power state machine stepped at each SYNC, the statusword,
faults (EMCY on entering and on leaving), and the reaction to a lost master (0x6007).

The transitions are :func:`drivers.cia402.state_machine.apply_controlword`, the table the master
walks the other way.
"""

from __future__ import annotations

from collections.abc import Sequence

from drivers.cia402 import frames as fr
from drivers.cia402.state_machine import (
    STATUS_BITS,
    SW_FOLLOWS_COMMAND,
    SW_INTERNAL_LIMIT,
    SW_REMOTE,
    SW_VOLTAGE_ENABLED,
    State,
    apply_controlword,
)
from sim_target.emulated.link import FrameLink
from sim_target.emulated.node import EmulatedDrive

_VOLTAGE_STATES = frozenset(
    {State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE}
)
# 0x6007 abort connection option code -> what the drive does (CiA 402 6.3.2).
ABORT_REACTIONS = {0: "none", 1: "fault", 2: "disable voltage", 3: "quick stop"}


# The statusword of an enabled drive (the cyclic case), without and with the internal-limit bit.
WORD_ENABLED = STATUS_BITS[State.OPERATION_ENABLED] | SW_REMOTE | SW_VOLTAGE_ENABLED | SW_FOLLOWS_COMMAND
WORD_LIMITED = WORD_ENABLED | SW_INTERNAL_LIMIT


def statusword(drive: EmulatedDrive) -> int:
    if drive.state is State.OPERATION_ENABLED:
        return WORD_LIMITED if drive.limited else WORD_ENABLED
    word = STATUS_BITS.get(drive.state, 0) | SW_REMOTE
    if drive.state in _VOLTAGE_STATES:
        word |= SW_VOLTAGE_ENABLED
    return word


def step(link: FrameLink, drive: EmulatedDrive) -> None:
    """At SYNC: a pending fault strikes, the latched controlword steps the state machine, the
    target torque is clipped to 0x6072 and applied in Operation Enabled only."""
    if drive.pending_fault is not None:
        code, drive.pending_fault = drive.pending_fault, None
        enter_fault(link, drive, code)
    if drive.nmt is not fr.NmtState.OPERATIONAL:
        drive.applied_permille = 0
        return
    if drive.state is State.OPERATION_ENABLED and drive.controlword & 0x008F == 0x000F:
        # The cyclic case: "enable operation" (bits 0-3 set, no fault reset) keeps an enabled
        # drive enabled (apply_controlword's table returns the same state); only the new target
        # torque is latched.
        drive.previous_controlword = drive.controlword
        limit = drive.max_torque_permille
        target = drive.target_permille
        drive.limited = not -limit <= target <= limit
        drive.applied_permille = max(-limit, min(limit, target))
        return
    previous_state = drive.state
    drive.state = apply_controlword(drive.state, drive.controlword, drive.previous_controlword, drive.quick_stop_option)
    drive.previous_controlword = drive.controlword
    if previous_state is State.FAULT and drive.state is not State.FAULT:
        drive.error_code = 0
        drive.error_register = 0
        link.emit(drive, fr.EMCY_BASE + drive.node_id, fr.encode_emcy(fr.EMCY_ERROR_RESET, 0))
    if drive.state is State.OPERATION_ENABLED:
        limit = drive.max_torque_permille
        target = drive.target_permille
        drive.limited = not -limit <= target <= limit
        drive.applied_permille = max(-limit, min(limit, target))
    else:
        drive.limited = False
        drive.applied_permille = 0


def step_all(link: FrameLink, drives: Sequence[EmulatedDrive], now_s: float) -> None:
    """At SYNC, every drive: the SYNC watch stamped (``now_s``), then :func:`step`, whose cyclic
    case (an enabled drive told to stay enabled, no fault pending) is inlined here: one call per
    SYNC for the bank rather than one per drive."""
    operational = fr.NmtState.OPERATIONAL
    enabled = State.OPERATION_ENABLED
    for drive in drives:
        if drive.sync_timeout_ms:
            drive.last_sync_s = now_s
        if (
            drive.state is enabled
            and drive.controlword & 0x008F == 0x000F
            and drive.pending_fault is None
            and drive.nmt is operational
        ):
            drive.previous_controlword = drive.controlword
            limit = drive.max_torque_permille  # 0x6072, unsigned
            target = drive.target_permille
            if -limit <= target <= limit:
                drive.limited = False
                drive.applied_permille = target
            else:
                drive.limited = True
                drive.applied_permille = limit if target > limit else -limit
        else:
            step(link, drive)


def enter_fault(link: FrameLink, drive: EmulatedDrive, code: int, register: int | None = None) -> None:
    drive.state = State.FAULT
    drive.applied_permille = 0
    drive.error_code = code
    drive.error_register = (
        register
        if register is not None
        else fr.ERROR_REGISTER_GENERIC | (fr.ERROR_REGISTER_CURRENT if 0x2000 <= code < 0x3000 else 0)
    )
    link.emit(drive, fr.EMCY_BASE + drive.node_id, fr.encode_emcy(code, drive.error_register))


def abort_connection(link: FrameLink, drive: EmulatedDrive, emcy_code: int) -> str:
    """The master is gone: react per 0x6007 (in Operation Enabled only) and say how."""
    reaction = ABORT_REACTIONS.get(drive.abort_connection_option, "fault")  # < 0: manufacturer: fault
    register = fr.ERROR_REGISTER_GENERIC | fr.ERROR_REGISTER_COMMUNICATION
    if reaction == "fault":
        enter_fault(link, drive, emcy_code, register)
        return reaction
    if reaction == "quick stop":
        drive.state = State.QUICK_STOP_ACTIVE  # torque off, brake on: the emulated stop is immediate
    elif reaction == "disable voltage":
        drive.state = State.SWITCH_ON_DISABLED
    drive.applied_permille = 0 if reaction != "none" else drive.applied_permille
    # The master's next controlword must not re-enable the drive by itself (cf. quick stop).
    drive.target_permille = 0 if reaction != "none" else drive.target_permille
    link.emit(drive, fr.EMCY_BASE + drive.node_id, fr.encode_emcy(emcy_code, register))
    return reaction
