"""Pure encode/decode of the CiA 301/402 frames the drive bus carries (everything but SDO).

Byte order is little-endian throughout (CiA 301). Decoders take the frame's data bytes and raise
:class:`MalformedFrameError` for a wrong length or an impossible value; they never look at the
bus. COB-IDs follow the CiA 301 predefined connection set (function code + node id).

PDO layouts (fixed; the driver writes the same mapping by SDO and the drive verifies it):

==========  =========  ====================================================================
frame       length     content
==========  =========  ====================================================================
RPDO1       4          controlword u16 (0x6040), target torque i16 (0x6071, ‰ of rated)
TPDO1       8          statusword u16 (0x6041), torque actual i16 (0x6077, ‰),
                       position actual i32 (0x6064, counts)
TPDO2       4          velocity actual i32 (0x606C, counts/s)
TPDO1 (FD)  12         TPDO1 + velocity actual i32: one CAN FD frame per drive
TPDO1 (FD,  16         the FD TPDO + SYNC counter echo u8 (0x2100) + 3 zero pad bytes (13
tagged)                data bytes travel in the next valid FD length): what the driver maps
==========  =========  ====================================================================

SYNC carries a counter byte 1..240 (CiA 301, 0x1019 = 240); the tagged FD TPDO echoes the counter
of the SYNC it answers, so the master never takes an older cycle's TPDO for this cycle's.
"""

from __future__ import annotations

import struct
from enum import IntEnum
from typing import Final, NamedTuple


class MalformedFrameError(ValueError):
    """A received frame whose length or content does not fit the protocol."""


# --- COB-IDs (CiA 301 predefined connection set) -------------------------------------------------

NMT_COB_ID: Final = 0x000
SYNC_COB_ID: Final = 0x080
EMCY_BASE: Final = 0x080
TPDO1_BASE: Final = 0x180
RPDO1_BASE: Final = 0x200
TPDO2_BASE: Final = 0x280
SDO_TX_BASE: Final = 0x580  # server -> client (drive answers)
SDO_RX_BASE: Final = 0x600  # client -> server (master asks)
HEARTBEAT_BASE: Final = 0x700

MAX_NODE_ID: Final = 127


def check_node_id(node_id: int) -> int:
    if not 1 <= node_id <= MAX_NODE_ID:
        raise ValueError(f"node id {node_id} outside 1..{MAX_NODE_ID}")
    return node_id


def split_cob_id(cob_id: int) -> tuple[int, int]:
    """(function code base, node id) of a predefined-set COB-ID; node id 0 for broadcast frames."""
    return cob_id & 0x780, cob_id & 0x07F


# --- NMT ------------------------------------------------------------------------------------------


class NmtCommand(IntEnum):
    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """State byte of a heartbeat (toggle bit masked); 0 is the boot-up message."""

    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


_NMT_STATE_VALUES: Final = frozenset(int(s) for s in NmtState)
_NMT_COMMAND_VALUES: Final = frozenset(int(c) for c in NmtCommand)


def encode_nmt(command: NmtCommand, node_id: int) -> bytes:
    """NMT command frame (COB-ID 0); node id 0 addresses every node."""
    if not 0 <= node_id <= MAX_NODE_ID:
        raise ValueError(f"NMT node id {node_id} outside 0..{MAX_NODE_ID}")
    return bytes((int(command), node_id))


def decode_nmt(data: bytes | bytearray) -> tuple[NmtCommand, int]:
    if len(data) != 2:
        raise MalformedFrameError(f"NMT frame has {len(data)} bytes, expected 2")
    if data[0] not in _NMT_COMMAND_VALUES:
        raise MalformedFrameError(f"unknown NMT command 0x{data[0]:02X}")
    if data[1] > MAX_NODE_ID:
        raise MalformedFrameError(f"NMT node id {data[1]} outside 0..{MAX_NODE_ID}")
    return NmtCommand(data[0]), data[1]


# --- SYNC -----------------------------------------------------------------------------------------


def encode_sync(counter: int | None = None) -> bytes:
    """SYNC: empty, or one counter byte 1..240 when 0x1019 (overflow value) is set."""
    if counter is None:
        return b""
    if not 1 <= counter <= 240:
        raise ValueError(f"SYNC counter {counter} outside 1..240")
    return bytes((counter,))


def decode_sync(data: bytes | bytearray) -> int | None:
    if len(data) == 0:
        return None
    if len(data) == 1 and 1 <= data[0] <= 240:
        return data[0]
    raise MalformedFrameError(f"SYNC frame with {len(data)} byte(s) {bytes(data).hex()}")


# --- Heartbeat / boot-up --------------------------------------------------------------------------


def encode_heartbeat(state: NmtState) -> bytes:
    return bytes((int(state),))


def decode_heartbeat(data: bytes | bytearray) -> NmtState:
    if len(data) != 1:
        raise MalformedFrameError(f"heartbeat has {len(data)} bytes, expected 1")
    value = data[0] & 0x7F  # bit 7 is the node-guarding toggle bit
    if value not in _NMT_STATE_VALUES:
        raise MalformedFrameError(f"heartbeat with unknown NMT state 0x{value:02X}")
    return NmtState(value)


# --- EMCY -----------------------------------------------------------------------------------------


class Emcy(NamedTuple):
    error_code: int  # CiA 301/402 error code; 0x0000 = error reset / no error
    error_register: int  # copy of 0x1001
    manufacturer: bytes  # 5 manufacturer-specific bytes


_EMCY: Final = struct.Struct("<HB5s")

# A few CiA 402 error codes the emulated drive raises; the driver reports any code it receives.
EMCY_ERROR_RESET: Final = 0x0000
EMCY_GENERIC: Final = 0x1000
EMCY_OVERCURRENT: Final = 0x2310
EMCY_OVERVOLTAGE: Final = 0x3210
EMCY_OVERTEMPERATURE: Final = 0x4310
EMCY_FOLLOWING_ERROR: Final = 0x8611
EMCY_COMMUNICATION: Final = 0x8100  # generic communication error; the drives' SYNC loss
EMCY_HEARTBEAT: Final = 0x8130  # life guard / heartbeat consumer timeout (the master's heartbeat)
EMCY_RPDO_TIMEOUT: Final = 0x8250  # no RPDO within its event timer (0x1400:05)

# What the driver's DriveFaultError says for the codes a drive of this layer sends.
EMCY_TEXT: Final[dict[int, str]] = {
    EMCY_GENERIC: "generic error",
    EMCY_OVERCURRENT: "overcurrent",
    EMCY_OVERVOLTAGE: "overvoltage",
    EMCY_OVERTEMPERATURE: "overtemperature",
    EMCY_FOLLOWING_ERROR: "following error",
    EMCY_COMMUNICATION: "communication error (no SYNC from the master within 0x2101)",
    EMCY_HEARTBEAT: "heartbeat consumer timeout (no heartbeat from the master within 0x1016)",
    EMCY_RPDO_TIMEOUT: "RPDO timeout (no set-point from the master within 0x1400:05)",
}

ERROR_REGISTER_GENERIC: Final = 0x01
ERROR_REGISTER_CURRENT: Final = 0x02
ERROR_REGISTER_TEMPERATURE: Final = 0x08
ERROR_REGISTER_COMMUNICATION: Final = 0x10


def encode_emcy(error_code: int, error_register: int, manufacturer: bytes = b"") -> bytes:
    if len(manufacturer) > 5:
        raise ValueError("EMCY manufacturer field is at most 5 bytes")
    return _EMCY.pack(error_code, error_register, manufacturer.ljust(5, b"\0"))


def decode_emcy(data: bytes | bytearray) -> Emcy:
    if len(data) != 8:
        raise MalformedFrameError(f"EMCY has {len(data)} bytes, expected 8")
    code, register, manufacturer = _EMCY.unpack(data)
    return Emcy(code, register, manufacturer)


# --- PDOs (the hot path: precompiled structs, no validation beyond length and range) --------------

_RPDO: Final = struct.Struct("<Hh")
_TPDO1: Final = struct.Struct("<Hhi")
_TPDO2: Final = struct.Struct("<i")
_TPDO_FD: Final = struct.Struct("<Hhii")
_TPDO_FD_SYNC: Final = struct.Struct("<HhiiB3x")  # 13 data bytes padded to the FD length 16

RPDO_LENGTH: Final = _RPDO.size
RPDO_STRUCT: Final = _RPDO  # (controlword, target torque ‰) of a received RPDO: an emulated drive's hot path
TPDO1_LENGTH: Final = _TPDO1.size
TPDO2_LENGTH: Final = _TPDO2.size
TPDO_FD_LENGTH: Final = _TPDO_FD.size
TPDO_FD_SYNC_LENGTH: Final = _TPDO_FD_SYNC.size

INT16_MIN: Final = -32768
INT16_MAX: Final = 32767

_pack_rpdo_into = _RPDO.pack_into
_pack_tpdo_fd_sync_into = _TPDO_FD_SYNC.pack_into
_unpack_rpdo = _RPDO.unpack
_unpack_tpdo1 = _TPDO1.unpack
_unpack_tpdo2 = _TPDO2.unpack
_unpack_tpdo_fd = _TPDO_FD.unpack
_unpack_tpdo_fd_sync = _TPDO_FD_SYNC.unpack
_new_tuple = tuple.__new__  # builds a NamedTuple from a tuple without its Python-level __new__ (hot path)


class RpdoData(NamedTuple):
    controlword: int
    target_torque_permille: int


class TpdoData(NamedTuple):
    statusword: int
    torque_actual_permille: int
    position_counts: int
    velocity_counts_s: int | None  # None in classical TPDO1 (it travels in TPDO2)


def encode_rpdo(controlword: int, target_torque_permille: int) -> bytes:
    """RPDO1; raises ValueError (struct.error) when a field does not fit its type."""
    try:
        return _RPDO.pack(controlword, target_torque_permille)
    except struct.error as exc:
        raise ValueError(f"RPDO field out of range: {exc}") from None


def encode_rpdo_into(buffer: bytearray | memoryview, controlword: int, target_torque_permille: int) -> None:
    """RPDO1 written into a reused frame buffer (the master's cycle: nothing allocated), or into
    a payload of a preallocated ipc datagram (:class:`drivers.ipc.frame.FrameBatch`)."""
    try:
        _pack_rpdo_into(buffer, 0, controlword, target_torque_permille)
    except struct.error as exc:
        raise ValueError(f"RPDO field out of range: {exc}") from None


def decode_rpdo(data: bytes | bytearray) -> RpdoData:
    if len(data) != RPDO_LENGTH:
        raise MalformedFrameError(f"RPDO1 has {len(data)} bytes, expected {RPDO_LENGTH}")
    return _new_tuple(RpdoData, _unpack_rpdo(data))


def encode_tpdo1(statusword: int, torque_actual_permille: int, position_counts: int) -> bytes:
    try:
        return _TPDO1.pack(statusword, torque_actual_permille, position_counts)
    except struct.error as exc:
        raise ValueError(f"TPDO1 field out of range: {exc}") from None


def encode_tpdo2(velocity_counts_s: int) -> bytes:
    try:
        return _TPDO2.pack(velocity_counts_s)
    except struct.error as exc:
        raise ValueError(f"TPDO2 field out of range: {exc}") from None


def encode_tpdo_fd(statusword: int, torque_actual_permille: int, position_counts: int, velocity_counts_s: int) -> bytes:
    try:
        return _TPDO_FD.pack(statusword, torque_actual_permille, position_counts, velocity_counts_s)
    except struct.error as exc:
        raise ValueError(f"FD TPDO field out of range: {exc}") from None


def decode_tpdo1(data: bytes | bytearray) -> TpdoData:
    if len(data) != TPDO1_LENGTH:
        raise MalformedFrameError(f"TPDO1 has {len(data)} bytes, expected {TPDO1_LENGTH}")
    return _new_tuple(TpdoData, (*_unpack_tpdo1(data), None))


def decode_tpdo2(data: bytes | bytearray) -> int:
    if len(data) != TPDO2_LENGTH:
        raise MalformedFrameError(f"TPDO2 has {len(data)} bytes, expected {TPDO2_LENGTH}")
    return int(_unpack_tpdo2(data)[0])


def encode_tpdo_fd_sync(
    statusword: int, torque_actual_permille: int, position_counts: int, velocity_counts_s: int, sync_counter: int
) -> bytes:
    try:
        return _TPDO_FD_SYNC.pack(statusword, torque_actual_permille, position_counts, velocity_counts_s, sync_counter)
    except struct.error as exc:
        raise ValueError(f"tagged FD TPDO field out of range: {exc}") from None


def encode_tpdo_fd_sync_into(
    buffer: bytearray,
    statusword: int,
    torque_actual_permille: int,
    position_counts: int,
    velocity_counts_s: int,
    sync_counter: int,
) -> None:
    """The tagged FD TPDO written into a reused 16-byte frame buffer (the drive's SYNC answer)."""
    try:
        _pack_tpdo_fd_sync_into(
            buffer, 0, statusword, torque_actual_permille, position_counts, velocity_counts_s, sync_counter
        )
    except struct.error as exc:
        raise ValueError(f"tagged FD TPDO field out of range: {exc}") from None


def decode_tpdo_fd_sync(data: bytes | bytearray) -> tuple[TpdoData, int]:
    """(feedback, SYNC counter echoed) of a tagged 16-byte FD TPDO."""
    if len(data) != TPDO_FD_SYNC_LENGTH:
        raise MalformedFrameError(f"tagged FD TPDO has {len(data)} bytes, expected {TPDO_FD_SYNC_LENGTH}")
    fields = _unpack_tpdo_fd_sync(data)
    return _new_tuple(TpdoData, fields[:4]), fields[4]


def unpack_tpdo_fd_sync(data: bytes | bytearray) -> tuple[int, int, int, int, int]:
    """(statusword, torque ‰, position, velocity, SYNC counter) of a tagged FD TPDO: the master's
    cycle reads the fields at once, so no :class:`TpdoData` is built (half the cost per frame)."""
    if len(data) != TPDO_FD_SYNC_LENGTH:
        raise MalformedFrameError(f"tagged FD TPDO has {len(data)} bytes, expected {TPDO_FD_SYNC_LENGTH}")
    fields: tuple[int, int, int, int, int] = _unpack_tpdo_fd_sync(data)
    return fields


def next_sync_counter(counter: int) -> int:
    """The SYNC counter after ``counter``: 1..240, wrapping (CiA 301 with 0x1019 = 240)."""
    return 1 if counter >= 240 else counter + 1


def decode_tpdo_fd(data: bytes | bytearray) -> TpdoData:
    # A CAN FD frame is padded to the next valid length (12 is one), so accept exactly 12.
    if len(data) != TPDO_FD_LENGTH:
        raise MalformedFrameError(f"FD TPDO has {len(data)} bytes, expected {TPDO_FD_LENGTH}")
    return _new_tuple(TpdoData, _unpack_tpdo_fd(data))
