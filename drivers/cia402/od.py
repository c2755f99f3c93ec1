"""The drive's object dictionary: the EDS shipped with the package, loading and checking it,
and the PDO mappings both ends agree on.
"""

from __future__ import annotations

import configparser
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import canopen
from canopen.objectdictionary import ObjectDictionary, ODVariable, datatypes

from drivers.errors import DriveConfigError

EDS_PATH: Final = Path(__file__).parent / "data" / "hil_cst_drive.eds"

# Object indices used by the driver and the emulated drive.
DEVICE_TYPE: Final = 0x1000
ERROR_REGISTER: Final = 0x1001
SYNC_COB_ID_OBJECT: Final = 0x1005
COMM_CYCLE_PERIOD: Final = 0x1006  # µs between SYNCs
CONSUMER_HEARTBEAT: Final = 0x1016  # sub n: node id << 16 | consumer time (ms)
HEARTBEAT_PRODUCER: Final = 0x1017
SYNC_OVERFLOW: Final = 0x1019
RPDO1_COMM: Final = 0x1400
RPDO1_MAP: Final = 0x1600
TPDO1_COMM: Final = 0x1800
TPDO2_COMM: Final = 0x1801
TPDO1_MAP: Final = 0x1A00
TPDO2_MAP: Final = 0x1A01
ERROR_CODE: Final = 0x603F
ABORT_CONNECTION_OPTION: Final = 0x6007  # CiA 402 reaction to losing the master (3: quick stop)
CONTROLWORD: Final = 0x6040
STATUSWORD: Final = 0x6041
QUICK_STOP_OPTION: Final = 0x605A
MODES_OF_OPERATION: Final = 0x6060
MODES_DISPLAY: Final = 0x6061
POSITION_ACTUAL: Final = 0x6064
VELOCITY_ACTUAL: Final = 0x606C
TARGET_TORQUE: Final = 0x6071
MAX_TORQUE: Final = 0x6072
RATED_TORQUE: Final = 0x6076
TORQUE_ACTUAL: Final = 0x6077
ENCODER_RESOLUTION: Final = 0x608F
SUPPORTED_MODES: Final = 0x6502
# Manufacturer object: the counter byte of the SYNC a drive's synchronous TPDO answers (0 when the
# SYNC carried none). Mapped last in the CAN FD TPDO, it tags the feedback with its cycle.
SYNC_COUNTER_ECHO: Final = 0x2100
SYNC_COUNTER_MAX: Final = 240  # 0x1019: the SYNC counter runs 1..240 (CiA 301)
# Manufacturer object: no SYNC for this many ms while Operation Enabled is a loss of the master
# (0: not watched). CiA 301 defines no SYNC consumer timeout; 0x1006 only states the period.
SYNC_TIMEOUT: Final = 0x2101

MODE_CYCLIC_SYNC_TORQUE: Final = 10
PDO_COB_ID_INVALID: Final = 0x8000_0000  # bit 31 of a PDO COB-ID: PDO disabled
TRANSMISSION_SYNC_EVERY: Final = 1  # synchronous, every SYNC


def mapping_entry(index: int, subindex: int, bits: int) -> int:
    """A PDO mapping entry: index << 16 | subindex << 8 | length in bits."""
    return (index << 16) | (subindex << 8) | bits


@dataclass(frozen=True)
class PdoLayout:
    """Mapping entries of RPDO1, TPDO1 and TPDO2 (empty: disabled)."""

    rpdo1: tuple[int, ...]
    tpdo1: tuple[int, ...]
    tpdo2: tuple[int, ...]


CLASSICAL_LAYOUT: Final = PdoLayout(
    rpdo1=(mapping_entry(CONTROLWORD, 0, 16), mapping_entry(TARGET_TORQUE, 0, 16)),
    tpdo1=(
        mapping_entry(STATUSWORD, 0, 16),
        mapping_entry(TORQUE_ACTUAL, 0, 16),
        mapping_entry(POSITION_ACTUAL, 0, 32),
    ),
    tpdo2=(mapping_entry(VELOCITY_ACTUAL, 0, 32),),
)

FD_LAYOUT: Final = PdoLayout(
    rpdo1=CLASSICAL_LAYOUT.rpdo1,
    tpdo1=CLASSICAL_LAYOUT.tpdo1 + (mapping_entry(VELOCITY_ACTUAL, 0, 32),),
    tpdo2=(),
)

# What the driver maps with CAN FD: FD_LAYOUT plus the SYNC counter echo (13 bytes, a 16-byte FD
# frame), so feedback that arrives in a later cycle is recognised as stale. The drive also accepts
# the untagged FD_LAYOUT (a plain 12-byte frame) from other masters.
FD_SYNC_LAYOUT: Final = PdoLayout(
    rpdo1=FD_LAYOUT.rpdo1,
    tpdo1=FD_LAYOUT.tpdo1 + (mapping_entry(SYNC_COUNTER_ECHO, 0, 8),),
    tpdo2=(),
)

# (index, subindex) -> data type every drive the runtime talks to must have.
REQUIRED_OBJECTS: Final[dict[tuple[int, int], int]] = {
    (DEVICE_TYPE, 0): datatypes.UNSIGNED32,
    (ERROR_REGISTER, 0): datatypes.UNSIGNED8,
    (HEARTBEAT_PRODUCER, 0): datatypes.UNSIGNED16,
    (RPDO1_COMM, 1): datatypes.UNSIGNED32,
    (RPDO1_COMM, 2): datatypes.UNSIGNED8,
    (RPDO1_MAP, 0): datatypes.UNSIGNED8,
    (RPDO1_MAP, 1): datatypes.UNSIGNED32,
    (RPDO1_MAP, 2): datatypes.UNSIGNED32,
    (TPDO1_COMM, 1): datatypes.UNSIGNED32,
    (TPDO1_COMM, 2): datatypes.UNSIGNED8,
    (TPDO2_COMM, 1): datatypes.UNSIGNED32,
    (TPDO2_COMM, 2): datatypes.UNSIGNED8,
    (TPDO1_MAP, 0): datatypes.UNSIGNED8,
    (TPDO1_MAP, 4): datatypes.UNSIGNED32,
    (TPDO1_MAP, 5): datatypes.UNSIGNED32,
    (TPDO2_MAP, 0): datatypes.UNSIGNED8,
    (TPDO2_MAP, 1): datatypes.UNSIGNED32,
    (ERROR_CODE, 0): datatypes.UNSIGNED16,
    (CONTROLWORD, 0): datatypes.UNSIGNED16,
    (STATUSWORD, 0): datatypes.UNSIGNED16,
    (QUICK_STOP_OPTION, 0): datatypes.INTEGER16,
    (MODES_OF_OPERATION, 0): datatypes.INTEGER8,
    (MODES_DISPLAY, 0): datatypes.INTEGER8,
    (POSITION_ACTUAL, 0): datatypes.INTEGER32,
    (VELOCITY_ACTUAL, 0): datatypes.INTEGER32,
    (TARGET_TORQUE, 0): datatypes.INTEGER16,
    (MAX_TORQUE, 0): datatypes.UNSIGNED16,
    (RATED_TORQUE, 0): datatypes.UNSIGNED32,
    (TORQUE_ACTUAL, 0): datatypes.INTEGER16,
    (ENCODER_RESOLUTION, 1): datatypes.UNSIGNED32,
    (ENCODER_RESOLUTION, 2): datatypes.UNSIGNED32,
    (SYNC_OVERFLOW, 0): datatypes.UNSIGNED8,
    (SYNC_COUNTER_ECHO, 0): datatypes.UNSIGNED8,
}


class EdsError(DriveConfigError):
    """An EDS that cannot describe a drive of this layer; one line naming the file and object."""


def lookup_variable(od: ObjectDictionary, index: int, subindex: int) -> ODVariable | None:
    """The variable at (index, subindex) of an object dictionary, or None."""
    try:
        entry = od[index]
    except KeyError:
        return None
    if isinstance(entry, ODVariable):
        return entry if subindex == 0 else None
    try:
        return entry[subindex]
    except KeyError:
        return None


def load_object_dictionary(node_id: int, eds_path: Path | str = EDS_PATH) -> ObjectDictionary:
    """Import and check an EDS; raises :class:`EdsError` naming the file and the bad object."""
    path = Path(eds_path)
    if not path.is_file():
        raise EdsError(f"{path}: EDS file not found")
    try:
        od = canopen.import_od(str(path), node_id)
    except (configparser.Error, KeyError, ValueError, UnicodeDecodeError) as exc:
        raise EdsError(f"{path}: unreadable EDS ({type(exc).__name__}: {exc})") from None
    for (index, subindex), data_type in REQUIRED_OBJECTS.items():
        var = lookup_variable(od, index, subindex)
        if var is None:
            raise EdsError(f"{path}: [{index:04X}] sub {subindex}: required object missing")
        if var.data_type != data_type:
            raise EdsError(
                f"{path}: [{index:04X}] sub {subindex}: DataType 0x{var.data_type:04X}, expected 0x{data_type:04X}"
            )
    return od
