"""The telemetry wire format: one public encoder/decoder (docs/telemetry.md, "Payloads").

Every payload starts with the same 24-byte little-endian header::

    offset size  field      dtype  meaning
    0      4     magic      S4     b"HILT"
    4      2     version    <u2    SCHEMA_VERSION; a decoder refuses any other
    6      1     kind       u1     1 state, 2 stats, 3 status, 4 event
    7      1     flags      u1     bit 0 GAP: samples were dropped just before this one
                                   bit 1 WARMUP: sent once at start-up, no data; skip it
    8      8     seq        <u8    state: the loop's cycle; others: a per-key counter
    16     8     t_ns       <i8    state: the loop's time of the cycle (ns); others: CLOCK_MONOTONIC

then the body:

    state   float64 blocks: fallback, compute_s, then q, qd, q_ref, qd_ref, tau, tau_fb (N each)
    stats   float64 block: one value per name in the schema's ``stats`` field list (NaN = not reported)
    status  UTF-8 JSON {"state", "fault", "bundle_id"}   (rare: text is fine)
    event   UTF-8 JSON {"kind", "cycle", "detail"}

The layouts (names, units, dtypes, offsets) are served as JSON by ``hil/<robot>/schema``
(:func:`build_schema`); :class:`Schema` reads that JSON back and decodes payloads against it,
refusing truncated payloads and unknown versions with a one-line :class:`TelemetryDecodeError`.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np

MAGIC = b"HILT"
SCHEMA_VERSION = 1
SCHEMA_NAME = "hil-telemetry"
HEADER = struct.Struct("<4sHBBQq")
HEADER_SIZE = HEADER.size  # 24, a multiple of 8: float64 blocks stay aligned
# The state header and its two scalars packed in one call on the loop thread.
STATE_HEAD = struct.Struct("<4sHBBQqdd")

FLAG_GAP = 0x01
FLAG_WARMUP = 0x02


class Kind(IntEnum):
    STATE = 1
    STATS = 2
    STATUS = 3
    EVENT = 4


# (name, unit) of the state payload, in wire order; scalars first, then N-joint blocks.
STATE_SCALARS: tuple[tuple[str, str], ...] = (("fallback", "1"), ("compute_s", "s"))
STATE_BLOCKS: tuple[tuple[str, str], ...] = (
    ("q", "rad"),
    ("qd", "rad/s"),
    ("q_ref", "rad"),
    ("qd_ref", "rad/s"),
    ("tau", "N*m"),
    ("tau_fb", "N*m"),
)
# The stats the runtime reports about once a second (names carry units); the sink fills the two
# telemetry_* counters itself. A runtime may add names through make_sink's info["stats_fields"].
STATS_FIELDS: tuple[str, ...] = (
    "rate_hz",
    "period_median_s",
    "period_p99_s",
    "period_max_s",
    "compute_median_s",
    "compute_p99_s",
    "compute_max_s",
    "cycles",
    "overruns",
    "fallbacks",
    "saturations",
    "bus_frames_sent",
    "bus_frames_received",
    "bus_dropped",
    "bus_late",
    "bus_malformed",
    "bus_emcy",
    "telemetry_sent",
    "telemetry_dropped",
)
STATUS_FIELDS: tuple[str, ...] = ("state", "fault", "bundle_id")
EVENT_FIELDS: tuple[str, ...] = ("kind", "cycle", "detail")
KEYS: dict[str, Kind] = {"state": Kind.STATE, "stats": Kind.STATS, "status": Kind.STATUS, "events": Kind.EVENT}


class TelemetryDecodeError(ValueError):
    """A payload or schema this decoder refuses; one line saying why."""

    exit_code = 2


def _unit_of(name: str) -> str:
    for suffix, unit in (("_hz", "Hz"), ("_s", "s"), ("_nm", "N*m"), ("_rad", "rad")):
        if name.endswith(suffix):
            return unit
    return "count"


def state_size(n_joints: int) -> int:
    return HEADER_SIZE + 8 * (len(STATE_SCALARS) + len(STATE_BLOCKS) * n_joints)


def build_schema(robot: str, joints: Sequence[str], stats_fields: Sequence[str] = STATS_FIELDS) -> dict[str, Any]:
    """The JSON the ``schema`` queryable serves: every payload's layout, with units and offsets."""
    n = len(joints)
    state_fields: list[dict[str, Any]] = []
    offset = HEADER_SIZE
    for name, unit in STATE_SCALARS:
        state_fields.append({"name": name, "unit": unit, "dtype": "<f8", "offset": offset, "count": 1})
        offset += 8
    for name, unit in STATE_BLOCKS:
        state_fields.append({"name": name, "unit": unit, "dtype": "<f8", "offset": offset, "count": n})
        offset += 8 * n
    stats = [
        {"name": name, "unit": _unit_of(name), "dtype": "<f8", "offset": HEADER_SIZE + 8 * i, "count": 1}
        for i, name in enumerate(stats_fields)
    ]
    return {
        "schema": SCHEMA_NAME,
        "schema_version": SCHEMA_VERSION,
        "byte_order": "little",
        "robot": robot,
        "joints": list(joints),
        "header": {
            "size": HEADER_SIZE,
            "magic": MAGIC.decode(),
            "fields": [
                {"name": "magic", "dtype": "S4", "offset": 0},
                {"name": "version", "dtype": "<u2", "offset": 4},
                {"name": "kind", "dtype": "u1", "offset": 6},
                {"name": "flags", "dtype": "u1", "offset": 7},
                {"name": "seq", "dtype": "<u8", "offset": 8},
                {"name": "t_ns", "dtype": "<i8", "offset": 16, "unit": "ns"},
            ],
            "flags": {"gap": FLAG_GAP, "warmup": FLAG_WARMUP},
        },
        "payloads": {
            "state": {"kind": int(Kind.STATE), "encoding": "float64", "size": offset, "fields": state_fields},
            "stats": {
                "kind": int(Kind.STATS),
                "encoding": "float64",
                "size": HEADER_SIZE + 8 * len(stats_fields),
                "fields": stats,
            },
            "status": {"kind": int(Kind.STATUS), "encoding": "json", "fields": list(STATUS_FIELDS)},
            "events": {"kind": int(Kind.EVENT), "encoding": "json", "fields": list(EVENT_FIELDS)},
        },
    }


@dataclass(frozen=True)
class Header:
    version: int
    kind: Kind
    flags: int
    seq: int
    t_ns: int

    @property
    def gap(self) -> bool:
        return bool(self.flags & FLAG_GAP)

    @property
    def warmup(self) -> bool:
        return bool(self.flags & FLAG_WARMUP)


def decode_header(payload: bytes | bytearray | memoryview) -> Header:
    """The header of any payload; refuses short payloads, a wrong magic and unknown versions."""
    if len(payload) < HEADER_SIZE:
        raise TelemetryDecodeError(
            f"payload refused: truncated ({len(payload)} bytes, the header alone is {HEADER_SIZE})"
        )
    magic, version, kind, flags, seq, t_ns = HEADER.unpack_from(payload, 0)
    if magic != MAGIC:
        raise TelemetryDecodeError(f"payload refused: magic {magic!r} is not {MAGIC!r}")
    if version != SCHEMA_VERSION:
        raise TelemetryDecodeError(
            f"payload refused: schema version {version} unknown (this decoder reads {SCHEMA_VERSION})"
        )
    try:
        kind_value = Kind(kind)
    except ValueError:
        raise TelemetryDecodeError(f"payload refused: unknown kind {kind}") from None
    return Header(version, kind_value, flags, seq, t_ns)


@dataclass(frozen=True)
class StateSample:
    header: Header
    values: dict[str, np.ndarray | float]  # q, qd, ... as (N,) arrays; fallback, compute_s floats

    def __getitem__(self, name: str) -> np.ndarray | float:
        return self.values[name]


@dataclass(frozen=True)
class _Field:
    name: str
    offset: int
    count: int


class Schema:
    """The layouts one runtime serves, read from its ``schema`` JSON; decodes its payloads."""

    def __init__(self, document: Mapping[str, Any]) -> None:
        if document.get("schema") != SCHEMA_NAME:
            raise TelemetryDecodeError(f"schema refused: {document.get('schema')!r} is not {SCHEMA_NAME!r}")
        version = document.get("schema_version")
        if version != SCHEMA_VERSION:
            raise TelemetryDecodeError(
                f"schema refused: version {version} unknown (this decoder reads {SCHEMA_VERSION})"
            )
        try:
            self.document = dict(document)
            self.robot = str(document["robot"])
            self.joints = tuple(str(name) for name in document["joints"])
            payloads = document["payloads"]
            self.state_size = int(payloads["state"]["size"])
            self.stats_size = int(payloads["stats"]["size"])
            self.state_fields = tuple(
                _Field(f["name"], int(f["offset"]), int(f["count"])) for f in payloads["state"]["fields"]
            )
            self.stats_fields = tuple(f["name"] for f in payloads["stats"]["fields"])
            self._stats_offsets = tuple(int(f["offset"]) for f in payloads["stats"]["fields"])
        except (KeyError, TypeError, ValueError) as exc:
            raise TelemetryDecodeError(f"schema refused: malformed ({type(exc).__name__}: {exc})") from None
        for field in self.state_fields:
            if field.offset < HEADER_SIZE or field.offset + 8 * field.count > self.state_size:
                raise TelemetryDecodeError(f"schema refused: state field {field.name!r} lies outside the payload")

    @classmethod
    def from_json(cls, text: str | bytes) -> Schema:
        try:
            document = json.loads(text)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise TelemetryDecodeError(f"schema refused: not JSON ({exc})") from None
        if not isinstance(document, dict):
            raise TelemetryDecodeError("schema refused: not a JSON object")
        return cls(document)

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    def _check(self, payload: bytes | bytearray | memoryview, kind: Kind, size: int | None) -> Header:
        header = decode_header(payload)
        if header.kind is not kind:
            raise TelemetryDecodeError(
                f"payload refused: kind {header.kind.name.lower()}, expected {kind.name.lower()}"
            )
        if header.warmup:
            return header
        if size is not None and len(payload) != size:
            what = "truncated" if len(payload) < size else "too long"
            raise TelemetryDecodeError(
                f"payload refused: {kind.name.lower()} {what} ({len(payload)} bytes, the schema says {size})"
            )
        return header

    def decode_state(self, payload: bytes | bytearray | memoryview) -> StateSample:
        header = self._check(payload, Kind.STATE, self.state_size)
        if header.warmup:
            return StateSample(header, {})
        values: dict[str, np.ndarray | float] = {}
        for field in self.state_fields:
            block = np.frombuffer(payload, dtype="<f8", count=field.count, offset=field.offset)
            values[field.name] = float(block[0]) if field.count == 1 and field.name in _SCALAR_NAMES else block
        return StateSample(header, values)

    def decode_state_row(self, payload: bytes | bytearray | memoryview) -> tuple[Header, np.ndarray]:
        """Header and the whole float64 body as one row (what the recorder stores)."""
        header = self._check(payload, Kind.STATE, self.state_size)
        if header.warmup:
            return header, np.empty(0)
        return header, np.frombuffer(payload, dtype="<f8", offset=HEADER_SIZE)

    def decode_stats(self, payload: bytes | bytearray | memoryview) -> tuple[Header, dict[str, float]]:
        header = self._check(payload, Kind.STATS, self.stats_size)
        if header.warmup:
            return header, {}
        return header, {
            name: struct.unpack_from("<d", payload, offset)[0]
            for name, offset in zip(self.stats_fields, self._stats_offsets, strict=True)
        }

    def decode_status(self, payload: bytes | bytearray | memoryview) -> tuple[Header, dict[str, Any]]:
        return _decode_json(payload, self._check(payload, Kind.STATUS, None), STATUS_FIELDS)

    def decode_event(self, payload: bytes | bytearray | memoryview) -> tuple[Header, dict[str, Any]]:
        return _decode_json(payload, self._check(payload, Kind.EVENT, None), EVENT_FIELDS)

    def body_columns(self) -> list[tuple[str, int, int]]:
        """(name, start, count) of each state field inside the float64 body (recorder layout)."""
        return [(f.name, (f.offset - HEADER_SIZE) // 8, f.count) for f in self.state_fields]


_SCALAR_NAMES = frozenset(name for name, _ in STATE_SCALARS)


def _decode_json(
    payload: bytes | bytearray | memoryview, header: Header, fields: tuple[str, ...]
) -> tuple[Header, dict[str, Any]]:
    if header.warmup:
        return header, {}
    try:
        body = json.loads(bytes(payload[HEADER_SIZE:]).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise TelemetryDecodeError(f"payload refused: {header.kind.name.lower()} body is not UTF-8 JSON") from None
    if not isinstance(body, dict) or any(name not in body for name in fields):
        raise TelemetryDecodeError(f"payload refused: {header.kind.name.lower()} body lacks {', '.join(fields)}")
    return header, body


# --- encoding (the publisher's side; tests use it too) -------------------------------------------


def encode_header(kind: Kind, seq: int, t_ns: int, flags: int = 0) -> bytes:
    return HEADER.pack(MAGIC, SCHEMA_VERSION, int(kind), flags, seq, t_ns)


def encode_state(
    seq: int,
    t_ns: int,
    blocks: Sequence[np.ndarray],
    fallback: float,
    compute_s: float,
    flags: int = 0,
) -> bytes:
    """One state payload (q, qd, q_ref, qd_ref, tau, tau_fb in ``blocks``, float64 arrays): the one
    encoder of the layout, called by the publisher's per-cycle hand-off (one join, no concatenated
    copy). A block that is not an array raises AttributeError; one of another dtype or length gives
    a payload of the wrong size, which the publisher refuses (counted)."""
    q, qd, q_ref, qd_ref, tau, tau_fb = blocks
    return b"".join(
        (
            STATE_HEAD.pack(MAGIC, SCHEMA_VERSION, _STATE_KIND, flags, seq, t_ns, fallback, compute_s),
            q.tobytes(),
            qd.tobytes(),
            q_ref.tobytes(),
            qd_ref.tobytes(),
            tau.tobytes(),
            tau_fb.tobytes(),
        )
    )


_STATE_KIND = int(Kind.STATE)


def encode_stats(seq: int, t_ns: int, values: Mapping[str, float], fields: Sequence[str] = STATS_FIELDS) -> bytes:
    body = np.array([_as_float(values.get(name)) for name in fields], dtype="<f8")
    return encode_header(Kind.STATS, seq, t_ns) + body.tobytes()


def encode_json(kind: Kind, seq: int, t_ns: int, body: Mapping[str, Any]) -> bytes:
    return encode_header(kind, seq, t_ns) + json.dumps(dict(body), separators=(",", ":"), default=str).encode("utf-8")


def _as_float(value: Any) -> float:
    """A stat as float64; missing or not a number (None, text) is NaN, never an exception."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")
