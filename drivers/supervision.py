"""Supervision: what keeps the arm safe when something stops answering.

On the master's side, every cycle (:meth:`drivers.joint_bus.JointBusBase.exchange`): a drive
without fresh feedback for more than ``max_missed_cycles`` consecutive cycles raises
:class:`FeedbackTimeoutError`; a drive that left Operation Enabled raises :class:`DriveFaultError`
(Fault) or :class:`DriveStateError`. The heartbeat consumer (:mod:`drivers.nmt`) and the EMCY
consumer (:mod:`drivers.emcy`) queue their errors on the network. Any run-time error first runs
:func:`fail_safe`: every drive that still answers is quick-stopped (at most ``SAFE_STOP_CYCLES``
cycles), never raising, so the caller gets the original error.

On the drives' side, for the master itself dying (:func:`configure_master_loss`, written at
start-up): each drive consumes the master's heartbeat (0x1016), watches its RPDO (event timer
0x1400:05) and, where the EDS has it, the SYNC (0x2101); any of them silent for
``comm_loss_timeout_s`` triggers the abort-connection option 0x6007 = 3, quick stop (CiA 402):
the drives stop the arm without the master.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from drivers.cia402 import od as odx
from drivers.config import DriveBusConfig
from drivers.errors import DriveConfigError, DriveError
from drivers.node import DriveNode
from drivers.pdo import set_rpdo_timeout
from drivers.profiles import p402
from drivers.sdo import SdoClient

log = logging.getLogger(__name__)

SAFE_STOP_CYCLES = 3  # quick-stop cycles sent after a run-time error (drives that answer confirm)
ABORT_CONNECTION_QUICK_STOP = 3  # 0x6007 = 3: quick stop (CiA 402 abort connection option code)


def configure_master_loss(sdo: SdoClient, node: DriveNode, config: DriveBusConfig) -> None:
    """Make the drive quick-stop on its own when the master goes silent (see module doc)."""
    if config.comm_loss_timeout_s is None:
        return
    node_id = node.node_id
    spec = node.joint.drive
    needed = [(odx.ABORT_CONNECTION_OPTION, 0)]
    if spec is None or sdo.variable(node_id, odx.RPDO1_COMM, 5) is None:
        needed.append((odx.CONSUMER_HEARTBEAT, 1))  # a vendor's drive may watch the RPDO alone
    for index, subindex in needed:
        if sdo.variable(node_id, index, subindex) is None:
            raise DriveConfigError(
                f"joints.{node.index}: the EDS of drive {node_id} has no 0x{index:04X}:{subindex:02X}, needed "
                "for the drive to stop on loss of the master (comm_loss_timeout_s: null runs without)"
            )
    timeout_ms = max(1, round(config.comm_loss_timeout_s * 1000))
    if sdo.variable(node_id, odx.CONSUMER_HEARTBEAT, 1) is not None:
        sdo.write(node_id, odx.CONSUMER_HEARTBEAT, 1, (config.master_node_id << 16) | timeout_ms)
    set_rpdo_timeout(sdo, node_id, timeout_ms)
    if sdo.variable(node_id, odx.COMM_CYCLE_PERIOD, 0) is not None:
        sdo.write(node_id, odx.COMM_CYCLE_PERIOD, 0, round(config.period_s * 1e6))
    # 0x2101 is the emulated drive's SYNC timeout; on a vendor's drive it is another object.
    if spec is None and sdo.variable(node_id, odx.SYNC_TIMEOUT, 0) is not None:
        sdo.write(node_id, odx.SYNC_TIMEOUT, 0, timeout_ms)
    option = ABORT_CONNECTION_QUICK_STOP
    if spec is not None and spec.reactions.abort_connection is not None:
        option = spec.reactions.abort_connection
    sdo.write(node_id, odx.ABORT_CONNECTION_OPTION, 0, option)


def fail_safe(cycle: p402.Cycle, nodes: Sequence[DriveNode]) -> None:
    """Quick-stop every drive that still answers (a few cycles at most); never raises."""
    n = len(nodes)
    codes, zeros_pm, zeros_nm = [p402.CW_QUICK_STOP] * n, [0] * n, np.zeros(n)
    for _ in range(SAFE_STOP_CYCLES):
        try:
            feedback = cycle(codes, zeros_pm, zeros_nm)
        except DriveError as exc:
            log.warning("quick stop after an error failed: %s", exc)
            return
        if all(
            not fresh or s in p402.QUICK_STOP_STATES or s in p402.FAULT_STATES
            for fresh, s in zip(feedback.fresh, feedback.states, strict=True)
        ):
            return
