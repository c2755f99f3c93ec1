"""The master's record of one drive: everything the services know about it, in one place.

One :class:`DriveNode` per joint (config order) replaces the per-service parallel lists: the
start-up writes its scaling, the cyclic exchange its last TPDO, supervision its heartbeat and
EMCY state. Fields written by a receiving thread are written only under the network's receive
lock (see :mod:`drivers.network`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import can
import canopen

from drivers.cia402 import frames as fr
from drivers.cia402.state_machine import State
from drivers.config import JointDriveConfig


@dataclass(slots=True, eq=False)
class DriveNode:
    index: int  # joint index in the config
    joint: JointDriveConfig
    fd: bool  # CAN FD layout (one tagged TPDO) or classical (TPDO1 + TPDO2)
    sdo_node: canopen.RemoteNode | None = None  # canopen's SDO client for this drive (start-up only)
    # Scaling: counts per radian read from 0x608F at start-up; ‰ of rated torque per N·m.
    counts_per_rad: float = 1.0  # signed: negative for a joint turning against its drive (polarity -1)
    zero_offset_rad: float = 0.0  # joint angle = drive angle - this (a drive section's zero_offset_rad)
    permille_per_nm: float = 1.0
    max_torque_nm: float = 0.0
    rpdo: can.Message = field(init=False)  # reused every cycle: RPDO1 packed in place

    # Cyclic feedback: the last accepted TPDO(s).
    statusword: int = 0
    torque_permille: int = 0
    position_counts: int = 0
    velocity_counts_s: int = 0
    tpdo1_cycle: int = -1  # cycle in which TPDO1 (or the FD TPDO) last arrived
    tpdo2_cycle: int = -1
    rx_time_s: float = 0.0  # time.monotonic() of the last accepted TPDO
    state: State = State.UNKNOWN  # CiA 402 state from the last fresh statusword

    # NMT error control (heartbeat consumer) and EMCY.
    nmt_state: fr.NmtState | None = None
    booted: bool = False
    last_heartbeat_s: float = 0.0
    heartbeat_lost: bool = False
    last_emcy_code: int = 0  # 0: none, or reset by the drive

    def __post_init__(self) -> None:
        self.permille_per_nm = 1e6 / self.joint.effective_rated_torque_mnm
        self.max_torque_nm = self.joint.max_torque_nm
        self.rpdo = can.Message(
            arbitration_id=fr.RPDO1_BASE + self.node_id,
            data=bytearray(fr.RPDO_LENGTH),
            is_extended_id=False,
            is_fd=self.fd,
            bitrate_switch=self.fd,
        )

    @property
    def node_id(self) -> int:
        return self.joint.node_id

    @property
    def fd_sync_echo(self) -> bool:
        """With CAN FD, does this drive's TPDO echo the SYNC counter (0x2100 of the emulated drive's
        EDS)? A vendor's drive (a ``drive`` section) sends the untagged 12-byte TPDO: its 0x2100 is
        the vendor's own object."""
        return self.fd and self.joint.drive is None
