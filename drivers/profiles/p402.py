"""CiA 402 (drives and motion control) on the master's side: the drive's configuration at
start-up and the power state machine walks (enable, quick stop, disable, fault reset).

The walks send one controlword per drive per control cycle through a ``cycle`` callable (one
:class:`~drivers.pdo.CyclicExchange` cycle): the drives step their state machine at each SYNC,
so a walk takes a few cycles. The transitions are the table of
:mod:`drivers.cia402.state_machine`, shared with the emulated drives.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence

import numpy as np

from drivers.cia402 import od as odx
from drivers.cia402.scaling import counts_per_rad_from_resolution
from drivers.cia402.state_machine import State, next_controlword
from drivers.config import DriveBusConfig
from drivers.errors import DriveConfigError, DriveError, DriveFaultError, DriveStateError
from drivers.feedback import DriveFeedback
from drivers.node import DriveNode
from drivers.sdo import SdoClient

log = logging.getLogger(__name__)

CW_ENABLE = 0x000F
CW_QUICK_STOP = 0x0002
CW_DISABLE_VOLTAGE = 0x0000
CW_SHUTDOWN = 0x0006
CW_FAULT_RESET = 0x0080
FAULT_STATES = frozenset({State.FAULT, State.FAULT_REACTION_ACTIVE})
QUICK_STOP_STATES = frozenset({State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED})
DEVICE_PROFILE = 402
CST_MODE_BIT = 1 << 9  # 0x6502 bit 9: cyclic synchronous torque supported

Cycle = Callable[[Sequence[int], Sequence[int], np.ndarray], DriveFeedback]


def configure(sdo: SdoClient, node: DriveNode, config: DriveBusConfig) -> None:
    """Check the drive is a CiA 402 drive that runs cyclic synchronous torque, adopt (or check)
    its encoder resolution, and write mode, torque scale and limits and the quick stop option
    (the reaction to a lost master is :func:`drivers.supervision.configure_master_loss`)."""
    i, joint, node_id = node.index, node.joint, node.node_id
    where = str(joint.drive.eds) if joint.drive is not None else f"joints.{i}"
    device_type = sdo.read_int(node_id, odx.DEVICE_TYPE)
    if device_type & 0xFFFF != DEVICE_PROFILE:
        raise DriveConfigError(
            f"{where}: node {node_id}: 0x1000:00: device type 0x{device_type:08X}, "
            f"profile {device_type & 0xFFFF}, not CiA 402"
        )
    modes = sdo.read_int(node_id, odx.SUPPORTED_MODES)
    if not modes & CST_MODE_BIT:
        raise DriveConfigError(
            f"{where}: node {node_id}: 0x6502:00: 0x{modes:08X}: the drive does not support cyclic synchronous torque"
        )
    if joint.drive is not None:  # a drive with its own EDS: scaling, reactions, SDO init list
        from drivers.commissioning import configure_spec

        configure_spec(sdo, node, config)
        return
    increments = sdo.read_int(node_id, odx.ENCODER_RESOLUTION, 1)
    revolutions = sdo.read_int(node_id, odx.ENCODER_RESOLUTION, 2)
    if joint.encoder_counts_per_rev is not None and joint.encoder_counts_per_rev * revolutions != increments:
        raise DriveConfigError(
            f"joints.{i}.encoder_counts_per_rev: {joint.encoder_counts_per_rev} but drive {node_id} "
            f"reports {increments} increments per {revolutions} revolution(s)"
        )
    node.counts_per_rad = counts_per_rad_from_resolution(increments, revolutions)
    sdo.write(node_id, odx.MODES_OF_OPERATION, 0, odx.MODE_CYCLIC_SYNC_TORQUE)
    sdo.write(node_id, odx.RATED_TORQUE, 0, joint.effective_rated_torque_mnm)
    sdo.write(node_id, odx.MAX_TORQUE, 0, joint.max_torque_permille)
    sdo.write(node_id, odx.QUICK_STOP_OPTION, 0, config.quick_stop_option)


def check_mode(sdo: SdoClient, node: DriveNode) -> None:
    display = sdo.read_int(node.node_id, odx.MODES_DISPLAY)
    if display != odx.MODE_CYCLIC_SYNC_TORQUE:
        raise DriveStateError(f"drive {node.node_id} runs mode {display}, not cyclic synchronous torque")


def step_towards(state: State, target: State) -> int:
    """The controlword of the next transition from ``state`` towards ``target``."""
    if state in (State.UNKNOWN, State.NOT_READY_TO_SWITCH_ON):
        return CW_SHUTDOWN
    controlword = next_controlword(state, target)
    return CW_ENABLE if controlword is None else controlword


def describe(nodes: Sequence[DriveNode]) -> str:
    return ", ".join(f"drive {node.node_id}: {node.state.value}" for node in nodes)


def walk_to_enabled(
    cycle: Cycle,
    nodes: Sequence[DriveNode],
    permille: Sequence[int],
    commanded_nm: np.ndarray,
    timeout_s: float,
    raise_pending: Callable[[], None],
) -> DriveFeedback:
    """Every drive to Operation Enabled, sending ``permille`` with each controlword; a drive in
    Fault raises :class:`DriveFaultError` (fault reset first)."""
    deadline = time.monotonic() + timeout_s
    while True:
        controlwords = []
        for node in nodes:
            if node.state in FAULT_STATES:
                raise DriveFaultError(node.node_id, node.last_emcy_code, "in Fault: call fault_reset() first")
            controlwords.append(step_towards(node.state, State.OPERATION_ENABLED))
        feedback = cycle(controlwords, permille, commanded_nm)
        raise_pending()
        if feedback.fresh.all() and all(s is State.OPERATION_ENABLED for s in feedback.states):
            return feedback
        if time.monotonic() > deadline:
            raise DriveStateError(f"not in operation enabled after {timeout_s} s: {describe(nodes)}")


def stop(
    cycle: Cycle, nodes: Sequence[DriveNode], controlword: int, targets: frozenset[State], timeout_s: float
) -> tuple[State, ...]:
    """Send ``controlword`` until every drive confirms a state in ``targets`` (or Fault); best
    effort: returns the states reached, logs instead of raising."""
    n = len(nodes)
    zeros_pm, zeros_nm = [0] * n, np.zeros(n)
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            feedback = cycle([controlword] * n, zeros_pm, zeros_nm)
        except DriveError as exc:  # the bus itself failed: nothing more to do here
            log.warning("stopping drives: %s", exc)
            return tuple(node.state for node in nodes)
        done = all(s in targets or s in FAULT_STATES for s in feedback.states)
        if feedback.fresh.all() and done:
            return feedback.states
        if time.monotonic() > deadline:
            log.warning("drives did not confirm the stop: %s", describe(nodes))
            return tuple(node.state for node in nodes)


def fault_reset(cycle: Cycle, nodes: Sequence[DriveNode], timeout_s: float) -> None:
    """Faulted drives to Switch On Disabled: disable voltage, then a rising edge of bit 7."""
    n = len(nodes)
    zeros_pm, zeros_nm = [0] * n, np.zeros(n)
    deadline = time.monotonic() + timeout_s
    cycle([CW_DISABLE_VOLTAGE] * n, zeros_pm, zeros_nm)
    while True:
        feedback = cycle([CW_FAULT_RESET] * n, zeros_pm, zeros_nm)
        if feedback.fresh.all() and not any(s in FAULT_STATES for s in feedback.states):
            return
        if time.monotonic() > deadline:
            raise DriveStateError(f"fault reset failed: {describe(nodes)}")
        cycle([CW_DISABLE_VOLTAGE] * n, zeros_pm, zeros_nm)
