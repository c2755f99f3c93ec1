"""PDOs on the drive's side: RPDO reception, the TPDO answer to each SYNC, and which mappings a
drive accepts (only the fixed layouts of :mod:`drivers.cia402.od`; anything else is refused with
SDO abort 0x06040041).

The TPDOs are encoded with :mod:`drivers.cia402.frames`, the codec the master decodes with.
"""

from __future__ import annotations

from time import monotonic as _monotonic

import can
from canopen.sdo.exceptions import SdoAbortedError

from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx
from drivers.cia402 import sdo as sdo_codes
from sim_target.emulated.link import FrameLink
from sim_target.emulated.node import EmulatedDrive
from sim_target.emulated.p402 import statusword

COMM_OF_MAP = {odx.RPDO1_MAP: odx.RPDO1_COMM, odx.TPDO1_MAP: odx.TPDO1_COMM, odx.TPDO2_MAP: odx.TPDO2_COMM}
MAP_OF_COMM = {comm: mapping for mapping, comm in COMM_OF_MAP.items()}
VALID_FIELD = {odx.RPDO1_COMM: "rpdo_valid", odx.TPDO1_COMM: "tpdo1_valid", odx.TPDO2_COMM: "tpdo2_valid"}
COB_BASE = {odx.RPDO1_COMM: fr.RPDO1_BASE, odx.TPDO1_COMM: fr.TPDO1_BASE, odx.TPDO2_COMM: fr.TPDO2_BASE}
LAYOUTS = {
    odx.RPDO1_MAP: (odx.CLASSICAL_LAYOUT.rpdo1, odx.FD_LAYOUT.rpdo1),
    odx.TPDO1_MAP: (odx.CLASSICAL_LAYOUT.tpdo1, odx.FD_LAYOUT.tpdo1, odx.FD_SYNC_LAYOUT.tpdo1),
    odx.TPDO2_MAP: (odx.CLASSICAL_LAYOUT.tpdo2, odx.FD_LAYOUT.tpdo2),
}


def on_rpdo(drive: EmulatedDrive, data: bytes | bytearray) -> bool:
    """Latch controlword and target torque (applied at the next SYNC); False when malformed.
    PDOs are ignored outside NMT operational (CiA 301). Feeds the RPDO watch (supervision)."""
    if drive.nmt is not fr.NmtState.OPERATIONAL or not drive.rpdo_valid:
        return True
    if len(data) != fr.RPDO_LENGTH:
        return False
    drive.controlword, drive.target_permille = fr.decode_rpdo(data)
    if drive.rpdo_timeout_ms:
        drive.last_rpdo_s = _monotonic()
    return True


def set_tpdo1_layout(drive: EmulatedDrive, n_entries: int) -> None:
    drive.fd_layout = n_entries in (len(odx.FD_LAYOUT.tpdo1), len(odx.FD_SYNC_LAYOUT.tpdo1))
    drive.fd_sync_echo = n_entries == len(odx.FD_SYNC_LAYOUT.tpdo1)
    drive.tpdo_msgs[fr.TPDO1_BASE] = can.Message(
        arbitration_id=fr.TPDO1_BASE + drive.node_id,
        data=bytearray(fr.TPDO_FD_SYNC_LENGTH),
        is_extended_id=False,
        is_fd=True,
        bitrate_switch=True,
    )


def send_tpdos(
    link: FrameLink,
    drive: EmulatedDrive,
    position_counts: int,
    velocity_counts: int,
    torque_permille: int,
    sync_counter: int,
) -> None:
    """This drive's answer to a SYNC, through its injected faults."""
    word = statusword(drive)
    policy = drive.policy
    if (
        drive.fd_sync_echo
        and drive.tpdo1_valid
        and not (policy.faults.active or policy.drop_next or policy.corrupt_next or policy.delay_next)
    ):
        # The hot path: encode into the drive's own message and send it, nothing allocated here.
        msg = drive.tpdo_msgs[fr.TPDO1_BASE]
        fr.encode_tpdo_fd_sync_into(msg.data, word, torque_permille, position_counts, velocity_counts, sync_counter)
        link.send(msg)
        return
    if policy.drop_next > 0:
        policy.drop_next -= 1
        link.dropped += 1
        return
    corrupt = policy.corrupt_next > 0
    if corrupt:
        policy.corrupt_next -= 1
    delay_s = 0.0
    if policy.delay_next > 0:
        policy.delay_next -= 1
        delay_s = policy.delay_next_s
    if drive.fd_layout:
        if drive.tpdo1_valid:
            if drive.fd_sync_echo:
                data = fr.encode_tpdo_fd_sync(word, torque_permille, position_counts, velocity_counts, sync_counter)
            else:
                data = fr.encode_tpdo_fd(word, torque_permille, position_counts, velocity_counts)
            link.emit(drive, fr.TPDO1_BASE + drive.node_id, data, fd=True, corrupt=corrupt, delay_s=delay_s)
        return
    if drive.tpdo1_valid:
        link.emit(
            drive,
            fr.TPDO1_BASE + drive.node_id,
            fr.encode_tpdo1(word, torque_permille, position_counts),
            corrupt=corrupt,
            delay_s=delay_s,
        )
    if drive.tpdo2_valid:
        link.emit(
            drive, fr.TPDO2_BASE + drive.node_id, fr.encode_tpdo2(velocity_counts), corrupt=corrupt, delay_s=delay_s
        )


def write_comm(drive: EmulatedDrive, index: int, subindex: int, value: int) -> bool:
    """A write to a PDO communication parameter (0x1400/0x1800/0x1801); False if not one."""
    if index not in COB_BASE:
        return False
    if subindex == 1:
        if value & 0x7FF != COB_BASE[index] + drive.node_id:
            raise SdoAbortedError(sdo_codes.ABORT_INVALID_VALUE)  # predefined set only
        valid = not value & odx.PDO_COB_ID_INVALID
        if valid and not drive.mappings[MAP_OF_COMM[index]]:
            raise SdoAbortedError(sdo_codes.ABORT_DEVICE_STATE)  # nothing mapped: cannot enable
        setattr(drive, VALID_FIELD[index], valid)
    elif subindex == 2:
        if value != odx.TRANSMISSION_SYNC_EVERY:
            raise SdoAbortedError(sdo_codes.ABORT_INVALID_VALUE)  # synchronous, every SYNC
    elif subindex == 5 and index == odx.RPDO1_COMM:
        drive.rpdo_timeout_ms = value  # event timer: the RPDO deadline (see supervision)
    return True


def write_mapping(drive: EmulatedDrive, index: int, subindex: int, value: int) -> bool:
    """A write to a PDO mapping (0x1600/0x1A00/0x1A01); False if not one. CiA 301 order: the PDO
    disabled, sub 0 cleared, entries written, sub 0 set to a count that makes a known layout."""
    if index not in LAYOUTS:
        return False
    if getattr(drive, VALID_FIELD[COMM_OF_MAP[index]]):
        raise SdoAbortedError(sdo_codes.ABORT_DEVICE_STATE)  # map only a disabled PDO
    layouts = LAYOUTS[index]
    if subindex == 0:
        if value == 0:
            drive.mappings[index] = []
            return True
        if not any(len(layout) == value for layout in layouts):
            raise SdoAbortedError(sdo_codes.ABORT_PDO_LENGTH)
        staged = drive.node.data_store.get(index, {})
        chosen = [int.from_bytes(staged[k], "little") if k in staged else None for k in range(1, value + 1)]
        if not any(list(layout) == chosen for layout in layouts):
            raise SdoAbortedError(sdo_codes.ABORT_NOT_MAPPABLE)
        drive.mappings[index] = chosen  # type: ignore[assignment]  # all entries present: checked above
        if index == odx.TPDO1_MAP:
            set_tpdo1_layout(drive, value)
        return True
    if drive.mappings[index]:
        raise SdoAbortedError(sdo_codes.ABORT_DEVICE_STATE)  # clear sub 0 first
    allowed = {layout[subindex - 1] for layout in layouts if len(layout) >= subindex}
    if value not in allowed and value != 0:
        raise SdoAbortedError(sdo_codes.ABORT_NOT_MAPPABLE)
    return True
