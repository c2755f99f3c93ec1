"""The Zenoh sink's loop side without a network: bytes offered == bytes the codec defines,
drop-oldest with a counter and a GAP flag, decimation, caller bugs counted not raised."""

from __future__ import annotations

import json
import logging
from typing import Any

import numpy as np
import pytest

from hil_runtime.telemetry import CycleState, TelemetryConfig, TelemetrySink, make_sink
from hil_runtime.telemetry.codec import FLAG_GAP, Schema, build_schema, encode_state
from hil_runtime.telemetry.publisher import ZenohTelemetry

JOINTS = ["a", "b", "c"]


class _FakePublisher:
    def __init__(self, fail: bool = False) -> None:
        self.payloads: list[bytes] = []
        self.fail = fail

    def put(self, payload: bytes | bytearray) -> None:
        if self.fail:
            raise RuntimeError("session closed")
        self.payloads.append(bytes(payload))


def _sink(**overrides: object) -> tuple[ZenohTelemetry, _FakePublisher]:
    config = TelemetryConfig.model_validate({"enabled": True, **overrides})
    sink = make_sink(config, "arm", {"joints": JOINTS, "bundle": {"bundle_id": "pd:abc"}})
    assert isinstance(sink, ZenohTelemetry)
    publisher = _FakePublisher()
    sink._publishers = {"state": publisher}
    return sink, publisher


def _offer(sink: TelemetrySink, seq: int) -> list[np.ndarray]:
    blocks = [np.full(3, seq + 0.1 * b) for b in range(6)]
    q, qd, q_ref, qd_ref, tau, tau_fb = blocks
    sink.offer_state(CycleState(seq, 1000 * seq, q, qd, q_ref, qd_ref, tau, tau_fb, 0.5, 2e-6))
    return blocks


def test_the_sink_satisfies_the_protocol() -> None:
    sink, _ = _sink()
    assert isinstance(sink, TelemetrySink)


def test_offered_bytes_are_the_codec_bytes() -> None:
    sink, publisher = _sink()
    blocks = _offer(sink, 7)
    sink._drain_state()
    assert publisher.payloads == [encode_state(7, 7000, blocks, 0.5, 2e-6)]
    sample = Schema(build_schema("arm", JOINTS)).decode_state(publisher.payloads[0])
    np.testing.assert_array_equal(sample["tau_fb"], blocks[5])


def test_the_caller_may_reuse_its_buffers() -> None:
    sink, publisher = _sink()
    q = np.zeros(3)
    zeros = np.zeros(3)
    for seq in range(3):
        q[:] = seq
        sink.offer_state(CycleState(seq, 0, q, zeros, zeros, zeros, zeros, zeros, 0.0, 0.0))
    sink._drain_state()
    schema = Schema(build_schema("arm", JOINTS))
    assert [float(np.asarray(schema.decode_state(p)["q"])[0]) for p in publisher.payloads] == [0.0, 1.0, 2.0]


def test_full_queue_drops_oldest_counts_and_flags_the_gap() -> None:
    sink, publisher = _sink(queue_size=4)
    for seq in range(10):
        _offer(sink, seq)
    assert sink.dropped == 6 and sink.counters["offered"] == 10
    sink._drain_state()
    schema = Schema(build_schema("arm", JOINTS))
    headers = [schema.decode_state(p).header for p in publisher.payloads]
    assert [h.seq for h in headers] == [6, 7, 8, 9]  # the newest kept
    assert [h.flags & FLAG_GAP for h in headers] == [FLAG_GAP, 0, 0, 0]
    assert sink._stats_values()["telemetry_dropped"] == 6.0
    assert sink._stats_values()["telemetry_sent"] == 4.0


def test_decimation_publishes_every_kth() -> None:
    sink, publisher = _sink(state_decimation=3)
    for seq in range(9):
        _offer(sink, seq)
    sink._drain_state()
    schema = Schema(build_schema("arm", JOINTS))
    assert [schema.decode_state(p).header.seq for p in publisher.payloads] == [2, 5, 8]


def test_caller_bugs_are_counted_never_raised(caplog: pytest.LogCaptureFixture) -> None:
    sink, publisher = _sink()
    zeros = np.zeros(3)
    caplog.set_level(logging.ERROR)
    sink.offer_state(CycleState(-1, 0, zeros, zeros, zeros, zeros, zeros, zeros, 0.0, 0.0))  # negative seq: u64
    not_an_array: Any = [0.0] * 3  # a list where an array belongs: the caller bug under test
    sink.offer_state(CycleState(1, 0, not_an_array, zeros, zeros, zeros, zeros, zeros, 0.0, 0.0))
    short = np.zeros(2)
    sink.offer_state(CycleState(2, 0, short, zeros, zeros, zeros, zeros, zeros, 0.0, 0.0))  # wrong joint count
    sink.offer_state(CycleState(3, 0, zeros.astype(np.float32), zeros, zeros, zeros, zeros, zeros, 0.0, 0.0))
    sink._drain_state()
    assert publisher.payloads == [] and sink.offer_errors == 4
    assert len([r for r in caplog.records if "refused" in r.getMessage()]) == 1  # said once, then counted


def test_put_failures_are_counted() -> None:
    sink, _ = _sink()
    sink._publishers = {"state": _FakePublisher(fail=True)}
    _offer(sink, 1)
    sink._drain_state()
    assert sink.publish_errors == 1 and sink.sent == 0


def test_status_changes_become_lifecycle_events() -> None:
    sink, _ = _sink(event_queue_size=2)
    _offer(sink, 41)
    sink.set_status("ACTIVE", None)
    sink.set_status("ACTIVE", None)  # no change, no event
    sink.set_status("FAULT", "heartbeat lost: node 3")
    events = list(sink._events)
    assert [(kind, cycle, detail) for _, kind, cycle, detail in events] == [
        ("lifecycle", 41, "UNCONFIGURED -> ACTIVE"),
        ("lifecycle", 41, "ACTIVE -> FAULT: heartbeat lost: node 3"),
    ]
    sink.event("fault", 42, "x")
    assert sink._events_dropped == 1 and len(sink._events) == 2


def test_queryable_documents() -> None:
    documents = {"joints": JOINTS, "config": {"period_s": 0.001}, "bundle": {"bundle_id": "pd:abc", "files": {}}}
    sink = make_sink(TelemetryConfig(enabled=True), "arm", documents)
    assert isinstance(sink, ZenohTelemetry)
    assert json.loads(sink._replies["schema"])["joints"] == JOINTS
    config = json.loads(sink._replies["config"])
    assert config["period_s"] == 0.001 and config["telemetry"]["enabled"] is True
    assert json.loads(sink._replies["bundle"])["bundle_id"] == "pd:abc" and sink.bundle_id == "pd:abc"


def test_extra_stats_names_join_the_schema() -> None:
    sink = make_sink(TelemetryConfig(enabled=True), "arm", {"joints": JOINTS, "stats_fields": ["tick", "rate_hz"]})
    assert isinstance(sink, ZenohTelemetry)
    names = [f["name"] for f in sink.schema["payloads"]["stats"]["fields"]]
    assert names[-1] == "tick" and names.count("rate_hz") == 1
