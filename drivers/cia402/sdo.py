"""Pure encode/decode of CiA 301 SDO frames (expedited transfers and abort) and the abort codes.

The driver's start-up configuration goes through the ``canopen`` library's SDO client (it also
does segmented transfers); these functions are the byte-level definition both ends are tested
against, and what the driver uses to read abort codes.
"""

from __future__ import annotations

import struct
from enum import Enum
from typing import Final, NamedTuple

from drivers.cia402.frames import MalformedFrameError

#: CiA 301 table 22, SDO abort codes.
ABORT_CODES: Final[dict[int, str]] = {
    0x05030000: "toggle bit not alternated",
    0x05040000: "SDO protocol timed out",
    0x05040001: "client/server command specifier not valid or unknown",
    0x05040002: "invalid block size",
    0x05040003: "invalid sequence number",
    0x05040004: "CRC error",
    0x05040005: "out of memory",
    0x06010000: "unsupported access to an object",
    0x06010001: "attempt to read a write only object",
    0x06010002: "attempt to write a read only object",
    0x06020000: "object does not exist in the object dictionary",
    0x06040041: "object cannot be mapped to the PDO",
    0x06040042: "number and length of mapped objects would exceed PDO length",
    0x06040043: "general parameter incompatibility",
    0x06040047: "general internal incompatibility in the device",
    0x06060000: "access failed due to a hardware error",
    0x06070010: "data type does not match, length of service parameter does not match",
    0x06070012: "data type does not match, length of service parameter too high",
    0x06070013: "data type does not match, length of service parameter too low",
    0x06090011: "sub-index does not exist",
    0x06090030: "invalid value for parameter",
    0x06090031: "value of parameter written too high",
    0x06090032: "value of parameter written too low",
    0x06090036: "maximum value is less than minimum value",
    0x060A0023: "resource not available: SDO connection",
    0x08000000: "general error",
    0x08000020: "data cannot be transferred or stored to the application",
    0x08000021: "data cannot be transferred or stored because of local control",
    0x08000022: "data cannot be transferred or stored because of the present device state",
    0x08000023: "object dictionary dynamic generation failed or no object dictionary present",
    0x08000024: "no data available",
}

ABORT_TIMEOUT: Final = 0x05040000
ABORT_BAD_COMMAND: Final = 0x05040001
ABORT_READ_ONLY: Final = 0x06010002
ABORT_NO_OBJECT: Final = 0x06020000
ABORT_NOT_MAPPABLE: Final = 0x06040041
ABORT_PDO_LENGTH: Final = 0x06040042
ABORT_LENGTH_MISMATCH: Final = 0x06070010
ABORT_NO_SUBINDEX: Final = 0x06090011
ABORT_INVALID_VALUE: Final = 0x06090030
ABORT_VALUE_TOO_HIGH: Final = 0x06090031
ABORT_VALUE_TOO_LOW: Final = 0x06090032
ABORT_DEVICE_STATE: Final = 0x08000022


def abort_code_text(code: int) -> str:
    return ABORT_CODES.get(code, "unknown abort code")


class SdoKind(Enum):
    UPLOAD_REQUEST = "upload request"
    DOWNLOAD_EXPEDITED = "expedited download"
    DOWNLOAD_SEGMENTED = "segmented download initiate"
    UPLOAD_EXPEDITED = "expedited upload response"
    UPLOAD_SEGMENTED = "segmented upload initiate response"
    DOWNLOAD_ACK = "download response"
    ABORT = "abort"


class SdoFrame(NamedTuple):
    kind: SdoKind
    index: int  # type: ignore[assignment]  # shadows tuple.index(): the CiA 301 name of the field wins
    subindex: int
    data: bytes  # expedited payload (1..4 bytes), else empty
    value: int  # abort code (ABORT), announced size (segmented), else 0


_HEADER: Final = struct.Struct("<BHB")
_ABORT: Final = struct.Struct("<BHBI")
_SIZE: Final = struct.Struct("<BHBI")

_CCS_DOWNLOAD: Final = 0x20
_CCS_UPLOAD: Final = 0x40
_SCS_UPLOAD: Final = 0x40
_SCS_DOWNLOAD: Final = 0x60
_ABORT_CS: Final = 0x80
_EXPEDITED: Final = 0x02
_SIZE_INDICATED: Final = 0x01


def _check_address(index: int, subindex: int) -> None:
    if not (0 <= index <= 0xFFFF and 0 <= subindex <= 0xFF):
        raise ValueError(f"SDO address 0x{index:X}:{subindex:X} out of range")


def _expedited(command_base: int, index: int, subindex: int, data: bytes) -> bytes:
    _check_address(index, subindex)
    if not 1 <= len(data) <= 4:
        raise ValueError(f"expedited SDO carries 1..4 bytes, got {len(data)}")
    command = command_base | ((4 - len(data)) << 2) | _EXPEDITED | _SIZE_INDICATED
    return _HEADER.pack(command, index, subindex) + bytes(data).ljust(4, b"\0")


def encode_upload_request(index: int, subindex: int) -> bytes:
    _check_address(index, subindex)
    return _HEADER.pack(_CCS_UPLOAD, index, subindex) + b"\0\0\0\0"


def encode_download_expedited(index: int, subindex: int, data: bytes) -> bytes:
    return _expedited(_CCS_DOWNLOAD, index, subindex, data)


def encode_upload_expedited_response(index: int, subindex: int, data: bytes) -> bytes:
    return _expedited(_SCS_UPLOAD, index, subindex, data)


def encode_download_response(index: int, subindex: int) -> bytes:
    _check_address(index, subindex)
    return _HEADER.pack(_SCS_DOWNLOAD, index, subindex) + b"\0\0\0\0"


def encode_abort(index: int, subindex: int, code: int) -> bytes:
    _check_address(index, subindex)
    return _ABORT.pack(_ABORT_CS, index, subindex, code)


def _split(data: bytes) -> tuple[int, int, int]:
    if len(data) != 8:
        raise MalformedFrameError(f"SDO frame has {len(data)} bytes, expected 8")
    return _HEADER.unpack_from(data)


def _payload(command: int, data: bytes) -> bytes:
    unused = (command >> 2) & 0x3 if command & _SIZE_INDICATED else 0
    return bytes(data[4 : 8 - unused])


class _Direction(NamedTuple):
    """One direction's command specifiers: the one that carries no data and the transfer's."""

    name: str
    plain_cs: int
    plain: SdoKind
    transfer_cs: int
    expedited: SdoKind
    segmented: SdoKind


_REQUEST: Final = _Direction(
    "request",
    _CCS_UPLOAD,
    SdoKind.UPLOAD_REQUEST,
    _CCS_DOWNLOAD,
    SdoKind.DOWNLOAD_EXPEDITED,
    SdoKind.DOWNLOAD_SEGMENTED,
)
_RESPONSE: Final = _Direction(
    "response", _SCS_DOWNLOAD, SdoKind.DOWNLOAD_ACK, _SCS_UPLOAD, SdoKind.UPLOAD_EXPEDITED, SdoKind.UPLOAD_SEGMENTED
)


def _decode(data: bytes, direction: _Direction) -> SdoFrame:
    command, index, subindex = _split(data)
    if command == _ABORT_CS:
        return SdoFrame(SdoKind.ABORT, index, subindex, b"", _ABORT.unpack(data)[3])
    cs = command & 0xE0
    if cs == direction.plain_cs:
        return SdoFrame(direction.plain, index, subindex, b"", 0)
    if cs == direction.transfer_cs:
        if command & _EXPEDITED:
            return SdoFrame(direction.expedited, index, subindex, _payload(command, data), 0)
        size = _SIZE.unpack(data)[3] if command & _SIZE_INDICATED else 0
        return SdoFrame(direction.segmented, index, subindex, b"", size)
    raise MalformedFrameError(f"SDO {direction.name} with unsupported command 0x{command:02X}")


def decode_request(data: bytes) -> SdoFrame:
    """A client -> server frame (COB-ID 0x600 + node)."""
    return _decode(data, _REQUEST)


def decode_response(data: bytes) -> SdoFrame:
    """A server -> client frame (COB-ID 0x580 + node)."""
    return _decode(data, _RESPONSE)
