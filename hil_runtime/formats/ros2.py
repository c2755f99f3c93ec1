"""ROS 2 message types without ROS 2: ``sensor_msgs/msg/JointState`` as CDR, its definition and its
RIHS01 type hash (docs/formats.md).

Used by the MCAP recorder (schema encoding ``ros2msg``, message encoding ``cdr``) and by the
rmw_zenoh-style ``/joint_states`` publisher. The encoder is ours (one ``struct`` per joint count,
no per-field Python work); the tests decode its bytes with two libraries we did not write
(mcap-ros2-support and rosbags) and compare the hash with rosbags' own computation.

CDR here is XCDR1 little-endian (``00 01 00 00`` encapsulation header), as rmw implementations
and rosbag2 write it: each primitive aligned to its size from the start of the body, strings as
uint32 length (terminating NUL included) + bytes + NUL, sequences as uint32 count + elements.
"""

from __future__ import annotations

import hashlib
import json
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np

JOINT_STATE = "sensor_msgs/msg/JointState"
# The DDS-mangled name rmw implementations put in key expressions and liveliness tokens.
JOINT_STATE_DDS = "sensor_msgs::msg::dds_::JointState_"

# The .msg texts (comments dropped), and the concatenated form MCAP's ros2msg schemas carry: the
# top-level definition, then each dependency after a line of 80 '=' and 'MSG: <type>'.
_DEFINITIONS = {
    "sensor_msgs/msg/JointState": (
        "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n"
    ),
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
}
_SEPARATOR = "=" * 80


def _short(type_name: str) -> str:
    package, _, name = type_name.split("/")
    return f"{package}/{name}"


JOINT_STATE_DEFINITION = "".join(
    [_DEFINITIONS[JOINT_STATE]]
    + [f"{_SEPARATOR}\nMSG: {_short(name)}\n{_DEFINITIONS[name]}" for name in ("std_msgs/msg/Header",)]
    + [f"{_SEPARATOR}\nMSG: {_short(name)}\n{_DEFINITIONS[name]}" for name in ("builtin_interfaces/msg/Time",)]
)

# --- RIHS01 (REP-2011): sha256 of the type description as JSON -------------------------------------

# type_description_interfaces/msg/FieldType ids; an unbounded sequence adds 144 (array 48, bounded 96).
_FIELD_TYPE_ID = {"nested": 1, "int32": 6, "uint32": 7, "float64": 11, "string": 17}
_UNBOUNDED_SEQUENCE = 144

# Each type's fields as (name, element type, is an unbounded sequence); nested types by full name.
_FIELDS: dict[str, list[tuple[str, str, bool]]] = {
    "sensor_msgs/msg/JointState": [
        ("header", "std_msgs/msg/Header", False),
        ("name", "string", True),
        ("position", "float64", True),
        ("velocity", "float64", True),
        ("effort", "float64", True),
    ],
    "std_msgs/msg/Header": [("stamp", "builtin_interfaces/msg/Time", False), ("frame_id", "string", False)],
    "builtin_interfaces/msg/Time": [("sec", "int32", False), ("nanosec", "uint32", False)],
}


def _type_description(type_name: str) -> dict[str, Any]:
    fields = []
    for name, element, sequence in _FIELDS[type_name]:
        nested = element if "/" in element else ""
        type_id = _FIELD_TYPE_ID["nested" if nested else element] + (_UNBOUNDED_SEQUENCE if sequence else 0)
        fields.append(
            {
                "name": name,
                "type": {"type_id": type_id, "capacity": 0, "string_capacity": 0, "nested_type_name": nested},
            }
        )
    return {"type_name": type_name, "fields": fields}


def _referenced(type_name: str, seen: set[str]) -> None:
    for _, element, _ in _FIELDS[type_name]:
        if "/" in element and element not in seen:
            seen.add(element)
            _referenced(element, seen)


def rihs01(type_name: str) -> str:
    """``RIHS01_<sha256>`` of a type this module describes: the hash ROS 2 (Iron and later) puts in
    type descriptions, rmw_zenoh key expressions and liveliness tokens. REP-2011: the JSON of
    ``{type_description, referenced_type_descriptions (sorted by name)}`` with default values left
    out, serialised with Python's default separators."""
    seen: set[str] = set()
    _referenced(type_name, seen)
    document = {
        "type_description": _type_description(type_name),
        "referenced_type_descriptions": [_type_description(name) for name in sorted(seen)],
    }
    return "RIHS01_" + hashlib.sha256(json.dumps(document).encode()).hexdigest()


# --- CDR -------------------------------------------------------------------------------------------

CDR_LE_HEADER = b"\x00\x01\x00\x00"
_STAMP = struct.Struct("<iI")


def _cdr_string(text: str, offset: int) -> tuple[bytes, int]:
    """(padding + uint32 length + bytes + NUL, new offset) for a string starting at ``offset``."""
    pad = b"\x00" * (-offset % 4)
    data = text.encode() + b"\x00"
    encoded = pad + struct.pack("<I", len(data)) + data
    return encoded, offset + len(encoded)


@dataclass(frozen=True)
class JointStateEncoder:
    """CDR of ``sensor_msgs/msg/JointState`` for a fixed list of joint names and frame id.

    Everything but the stamp and the three arrays is constant, so one message is
    ``struct.pack`` of the stamp, the constant middle and the arrays with their fixed padding.
    """

    joint_names: tuple[str, ...]
    frame_id: str = ""
    # Made by __post_init__ from the two above (frozen: set there with object.__setattr__).
    _middle: bytes = field(init=False, repr=False, compare=False)
    _prefixes: tuple[bytes, bytes, bytes] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Offsets count from the start of the body (after the 4-byte encapsulation header).
        offset = 8  # stamp: int32 sec, uint32 nanosec
        middle, offset = _cdr_string(self.frame_id, offset)
        pad = -offset % 4
        middle += b"\x00" * pad + struct.pack("<I", len(self.joint_names))
        offset += pad + 4
        for name in self.joint_names:
            encoded, offset = _cdr_string(name, offset)
            middle += encoded
        n = len(self.joint_names)
        prefixes = []
        for _ in range(3):  # position, velocity, effort: uint32 count (align 4), float64s (align 8)
            pad_count = -offset % 4
            offset += pad_count + 4
            pad_values = -offset % 8 if n else 0
            offset += pad_values + 8 * n
            prefixes.append(b"\x00" * pad_count + struct.pack("<I", n) + b"\x00" * pad_values)
        object.__setattr__(self, "_middle", middle)
        object.__setattr__(self, "_prefixes", tuple(prefixes))
        object.__setattr__(self, "size", 4 + offset)

    def encode(self, stamp_ns: int, position: np.ndarray, velocity: np.ndarray, effort: np.ndarray) -> bytes:
        """One message from three (N,) float64 arrays; ``stamp_ns`` becomes header.stamp."""
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        p0, p1, p2 = self._prefixes
        return b"".join(
            (
                CDR_LE_HEADER,
                _STAMP.pack(sec, nanosec),
                self._middle,
                p0,
                np.asarray(position, dtype="<f8").tobytes(),
                p1,
                np.asarray(velocity, dtype="<f8").tobytes(),
                p2,
                np.asarray(effort, dtype="<f8").tobytes(),
            )
        )


def decode_joint_state(data: bytes) -> dict[str, Any]:
    """Our own reader of the encoder's output (the tests also use independent ones): for round trips
    in tools that must not depend on an optional package. Raises ValueError on malformed bytes."""
    if data[:4] != CDR_LE_HEADER:
        raise ValueError("not little-endian CDR (encapsulation header)")
    body = memoryview(data)[4:]
    offset = 0

    def take(fmt: str) -> tuple[Any, ...]:
        nonlocal offset
        size = struct.calcsize("<" + fmt)
        offset += -offset % min(size, 8) if fmt in ("I", "i", "d") else 0
        if offset + size > len(body):
            raise ValueError("truncated CDR")
        values = struct.unpack_from("<" + fmt, body, offset)
        offset += size
        return values

    def string() -> str:
        nonlocal offset
        (length,) = take("I")
        if length == 0 or offset + length > len(body):
            raise ValueError("bad CDR string")
        text = bytes(body[offset : offset + length - 1]).decode()
        offset += length
        return text

    sec, nanosec = take("i")[0], take("I")[0]
    frame_id = string()
    names = [string() for _ in range(take("I")[0])]
    arrays = []
    for _ in range(3):
        (count,) = take("I")
        offset += -offset % 8 if count else 0
        if offset + 8 * count > len(body):
            raise ValueError("truncated CDR")
        arrays.append(np.frombuffer(body, dtype="<f8", count=count, offset=offset).copy())
        offset += 8 * count
    return {
        "stamp_ns": sec * 1_000_000_000 + nanosec,
        "frame_id": frame_id,
        "name": names,
        "position": arrays[0],
        "velocity": arrays[1],
        "effort": arrays[2],
    }
