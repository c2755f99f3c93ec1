"""The wire format: layouts in the schema, byte-exact round trips, and one-line refusals."""

from __future__ import annotations

import json
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil_runtime.telemetry.codec import (
    FLAG_GAP,
    FLAG_WARMUP,
    HEADER_SIZE,
    MAGIC,
    SCHEMA_VERSION,
    STATS_FIELDS,
    Kind,
    Schema,
    TelemetryDecodeError,
    build_schema,
    decode_header,
    encode_header,
    encode_json,
    encode_state,
    encode_stats,
    state_size,
)

JOINTS = ["j1", "j2", "j3"]


@pytest.fixture()
def schema() -> Schema:
    # Through JSON, as a subscriber gets it from the queryable.
    return Schema.from_json(json.dumps(build_schema("arm", JOINTS)))


def _blocks(n: int = 3) -> list[np.ndarray]:
    return [np.arange(n, dtype=float) + 10.0 * b for b in range(6)]


def test_header_bytes_are_the_documented_layout() -> None:
    raw = encode_header(Kind.STATS, seq=0x0102030405060708, t_ns=-5, flags=FLAG_GAP)
    assert len(raw) == HEADER_SIZE == 24
    assert raw[:4] == b"HILT"
    assert raw[4:6] == SCHEMA_VERSION.to_bytes(2, "little")
    assert raw[6] == 2 and raw[7] == FLAG_GAP
    assert raw[8:16] == bytes([8, 7, 6, 5, 4, 3, 2, 1])  # little-endian u64
    assert struct.unpack("<q", raw[16:24])[0] == -5


def test_state_layout_offsets_and_size() -> None:
    document = build_schema("arm", JOINTS)
    fields = {f["name"]: f for f in document["payloads"]["state"]["fields"]}
    names = [f["name"] for f in document["payloads"]["state"]["fields"]]
    assert names == "fallback compute_s q qd q_ref qd_ref tau tau_fb".split()
    assert fields["fallback"]["offset"] == 24 and fields["compute_s"]["offset"] == 32
    assert fields["q"]["offset"] == 40 and fields["q"]["count"] == 3
    assert fields["tau_fb"]["offset"] == 40 + 5 * 24
    assert fields["tau"]["unit"] == "N*m" and fields["qd"]["unit"] == "rad/s"
    assert document["payloads"]["state"]["size"] == state_size(3) == 24 + 8 * (2 + 18)
    stats = document["payloads"]["stats"]
    assert [f["name"] for f in stats["fields"]] == list(STATS_FIELDS)
    assert stats["size"] == 24 + 8 * len(STATS_FIELDS)


def test_state_round_trip(schema: Schema) -> None:
    blocks = _blocks()
    payload = encode_state(42, 123_456_789, blocks, 0.25, 1.5e-5)
    assert len(payload) == schema.state_size
    sample = schema.decode_state(payload)
    assert sample.header.seq == 42 and sample.header.t_ns == 123_456_789 and sample.header.kind is Kind.STATE
    assert not sample.header.gap and not sample.header.warmup
    for name, block in zip(("q", "qd", "q_ref", "qd_ref", "tau", "tau_fb"), blocks, strict=True):
        np.testing.assert_array_equal(sample[name], block)
    assert sample["fallback"] == 0.25 and sample["compute_s"] == 1.5e-5
    header, row = schema.decode_state_row(payload)
    assert header.seq == 42 and row.shape == (20,) and row[0] == 0.25


def test_stats_status_event_round_trip(schema: Schema) -> None:
    header, stats = schema.decode_stats(encode_stats(3, 9, {"rate_hz": 999.5, "overruns": 2}))
    assert header.seq == 3 and stats["rate_hz"] == 999.5 and stats["overruns"] == 2.0
    assert np.isnan(stats["compute_p99_s"])  # not reported -> NaN, never a made-up zero
    header, body = schema.decode_status(
        encode_json(Kind.STATUS, 1, 2, {"state": "FAULT", "fault": "x", "bundle_id": "b"})
    )
    assert body == {"state": "FAULT", "fault": "x", "bundle_id": "b"}
    header, body = schema.decode_event(encode_json(Kind.EVENT, 1, 2, {"kind": "fault", "cycle": 7, "detail": "emcy"}))
    assert body["cycle"] == 7


def test_warmup_payloads_decode_empty(schema: Schema) -> None:
    warm = encode_header(Kind.STATE, 0, 0, FLAG_WARMUP)
    sample = schema.decode_state(warm)
    assert sample.header.warmup and sample.values == {}


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda p: p[:-8], "payload refused: state truncated (320 bytes, the schema says 328)"),
        (lambda p: p[:10], "payload refused: truncated (10 bytes, the header alone is 24)"),
        (lambda p: p + b"\0" * 8, "payload refused: state too long (336 bytes, the schema says 328)"),
        (
            lambda p: p[:4] + (SCHEMA_VERSION + 1).to_bytes(2, "little") + p[6:],
            f"payload refused: schema version {SCHEMA_VERSION + 1} unknown (this decoder reads {SCHEMA_VERSION})",
        ),
        (lambda p: b"XXXX" + p[4:], "payload refused: magic b'XXXX' is not b'HILT'"),
        (lambda p: p[:6] + bytes([9]) + p[7:], "payload refused: unknown kind 9"),
        (lambda p: p[:6] + bytes([2]) + p[7:], "payload refused: kind stats, expected state"),
    ],
)
def test_decoder_refuses_in_one_line(mutate: Callable[[bytes], bytes], message: str) -> None:
    schema = Schema(build_schema("arm", ["a", "b", "c", "d", "e", "f"]))
    payload = encode_state(1, 1, _blocks(6), 0.0, 0.0)
    with pytest.raises(TelemetryDecodeError) as info:
        schema.decode_state(mutate(payload))
    assert str(info.value) == message
    assert "\n" not in str(info.value) and info.value.exit_code == 2


def test_json_bodies_are_checked(schema: Schema) -> None:
    with pytest.raises(TelemetryDecodeError, match="status body lacks state, fault, bundle_id"):
        schema.decode_status(encode_json(Kind.STATUS, 1, 1, {"state": "ACTIVE"}))
    with pytest.raises(TelemetryDecodeError, match="event body is not UTF-8 JSON"):
        schema.decode_event(encode_header(Kind.EVENT, 1, 1) + b"\xff{")


def test_schema_of_another_version_or_shape_is_refused() -> None:
    document = build_schema("arm", JOINTS)
    with pytest.raises(TelemetryDecodeError, match="schema refused: version 2 unknown"):
        Schema({**document, "schema_version": 2})
    with pytest.raises(TelemetryDecodeError, match="schema refused: 'other' is not 'hil-telemetry'"):
        Schema({**document, "schema": "other"})
    broken = json.loads(json.dumps(document))
    broken["payloads"]["state"]["fields"][2]["offset"] = 10_000
    with pytest.raises(TelemetryDecodeError, match="state field 'q' lies outside the payload"):
        Schema(broken)
    with pytest.raises(TelemetryDecodeError, match="schema refused: not JSON"):
        Schema.from_json(b"{nope")
    del broken["payloads"]
    with pytest.raises(TelemetryDecodeError, match="schema refused: malformed"):
        Schema(broken)


def test_decode_header_on_any_payload() -> None:
    header = decode_header(encode_json(Kind.EVENT, 5, 6, {"kind": "k", "cycle": 1, "detail": ""}))
    assert header.kind is Kind.EVENT and header.seq == 5
    assert MAGIC == b"HILT"


def test_stats_that_are_not_numbers_become_nan(schema: Schema) -> None:
    not_numbers: dict[str, Any] = {"rate_hz": None, "overruns": "x", "cycles": True}  # wrong types on purpose
    _, stats = schema.decode_stats(encode_stats(1, 1, not_numbers))
    assert np.isnan(stats["rate_hz"]) and np.isnan(stats["overruns"]) and stats["cycles"] == 1.0
    _, body = schema.decode_event(encode_json(Kind.EVENT, 1, 1, {"kind": "k", "cycle": 1, "detail": Path("/x")}))
    assert body["detail"] == "/x"
