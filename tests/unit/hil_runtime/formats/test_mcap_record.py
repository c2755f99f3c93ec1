"""MCAP records read back by mcap's own reader and mcap-ros2-support's decoder (not ours)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil_runtime.formats.mcap_record import (
    McapRecorder,
    McapRecordError,
    McapSink,
    read_mcap_record,
    save_mcap_record,
)
from hil_runtime.outputs import OutputError
from hil_runtime.record import check_record_path
from hil_runtime.telemetry.sink import CycleState, FanOutTelemetry, NullTelemetry

mcap_reader = pytest.importorskip("mcap.reader")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")

JOINTS = ("j1", "j2", "j3")
COLUMNS = ("q", "qd", "q_ref", "qd_ref", "tau", "tau_fb")
URDF = b"<robot name='arm'/>"


def _sample(k: int) -> CycleState:
    n = len(JOINTS)
    base = np.arange(n, dtype=float) + 0.001 * k
    return CycleState(
        seq=k,
        t_ns=1_000_000_000 + 1_000_000 * k,
        q=base,
        qd=base + 10,
        q_ref=base + 20,
        qd_ref=base + 30,
        tau=base + 40,
        tau_fb=base + 50,
        fallback=0.5 if k % 2 else 0.0,
        compute_s=1e-5 * k,
    )


def _sink(path: Path, queue_size: int = 20_000) -> McapSink:
    recorder = McapRecorder(path, JOINTS, "arm", urdf=("arm.urdf", URDF), manifest=b'{"schema": 2}')
    return McapSink(recorder, queue_size=queue_size, drain_period_s=0.001)


def _messages(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """Per topic: (log time, message), a CDR one decoded lazily, a JSON one as parsed (Any: both untyped)."""
    by_topic: dict[str, list[tuple[int, Any]]] = {}
    decoders: dict[int, Callable[[bytes], Any]] = {}
    factory = mcap_ros2_decoder.DecoderFactory()
    with path.open("rb") as stream:
        reader = mcap_reader.make_reader(stream, decoder_factories=[mcap_ros2_decoder.DecoderFactory()])
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding == "cdr":
                assert schema is not None and schema.encoding == "ros2msg"
                decode = decoders.setdefault(schema.id, factory.decoder_for("cdr", schema))
                decoded: Any = Lazy(decode, message.data)  # decoded when a test looks (20k messages)
            else:
                assert channel.message_encoding == "json" and schema is not None and schema.encoding == "jsonschema"
                decoded = json.loads(message.data)
            by_topic.setdefault(channel.topic, []).append((message.log_time, decoded))
    return by_topic


class Lazy:
    """A CDR message decoded by mcap-ros2-support on first attribute access."""

    def __init__(self, decode: Callable[[bytes], Any], data: bytes) -> None:
        self._decode, self._data, self._msg = decode, data, None

    def __getattr__(self, name: str) -> Any:
        if self._msg is None:
            self._msg = self._decode(self._data)
        return getattr(self._msg, name)


def test_a_run_through_the_sink_reads_back_with_standard_types_urdf_and_every_sample(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    sink = FanOutTelemetry(NullTelemetry(), _sink(path))
    sink.start()
    sink.set_status("ACTIVE", None)
    cycles = 10_000  # 10 s at 1 kHz
    for k in range(cycles):
        sink.offer_state(_sample(k))  # the loop reuses its arrays: the sink must have copied
    sink.offer_stats({"rate_hz": 1000.0, "overruns": 0, "compute_p99_s": float("nan")})
    sink.event("fault", 42, "heartbeat lost: node 3")
    sink.close()

    topics = _messages(path)
    states = topics["/joint_states"]
    assert len(states) == cycles and len(topics["/joint_reference"]) == cycles
    assert [t for t, _ in states] == [1_000_000_000 + 1_000_000 * k for k in range(cycles)]  # the runtime's clock
    t, msg = states[1234]
    assert list(msg.name) == list(JOINTS)
    assert msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == t
    np.testing.assert_array_equal(msg.position, _sample(1234).q)
    np.testing.assert_array_equal(msg.effort, _sample(1234).tau)
    ref = topics["/joint_reference"][1234][1]
    np.testing.assert_array_equal(ref.position, _sample(1234).q_ref)
    np.testing.assert_array_equal(ref.effort, _sample(1234).tau_fb)
    cycle = [body for _, body in topics["/hil/cycle"]]
    assert [c["seq"] for c in cycle] == list(range(cycles))
    assert cycle[7] == {"seq": 7, "fallback": 0.5, "compute_s": _sample(7).compute_s}
    assert topics["/hil/stats"][0][1] == {"rate_hz": 1000.0, "overruns": 0.0, "compute_p99_s": None}
    assert topics["/hil/status"][0][1] == {"state": "ACTIVE", "fault": None}
    assert topics["/hil/events"][0][1] == {"kind": "fault", "cycle": 42, "detail": "heartbeat lost: node 3"}

    with path.open("rb") as stream:
        reader = mcap_reader.make_reader(stream)
        attachments = {a.name: (a.media_type, a.data) for a in reader.iter_attachments()}
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert attachments["arm.urdf"] == ("application/xml", URDF)
    assert attachments["manifest.json"][0] == "application/json"
    assert json.loads(metadata["hil"]["joints"]) == list(JOINTS)
    assert metadata["recording"] == {"states_written": str(cycles), "dropped": "0"}
    assert not list(tmp_path.glob(".*partial"))  # renamed into place


def test_a_full_queue_drops_new_samples_and_counts_them(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    sink = _sink(path, queue_size=10)
    sink._thread = None  # never drained before close: the queue fills
    for k in range(25):
        sink.offer_state(_sample(k))
    assert sink.dropped == 15
    sink.start()
    sink.close()
    with path.open("rb") as stream:
        reader = mcap_reader.make_reader(stream)
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        seqs = [json.loads(m.data)["seq"] for _, _, m in reader.iter_messages(topics=["/hil/cycle"])]
    assert seqs == list(range(10))
    assert metadata["recording"]["dropped"] == "15"


def test_a_sink_never_started_leaves_no_file(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    _sink(path).close()
    assert list(tmp_path.iterdir()) == []


def test_the_plot_reader_gets_the_columns_back(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    samples = [_sample(k) for k in range(50)]
    arrays = {
        "seq": np.arange(50, dtype=np.uint64),
        "t_ns": np.array([s.t_ns for s in samples]),
        "fallback": np.array([s.fallback for s in samples]),
        "compute_s": np.array([s.compute_s for s in samples]),
        **{
            name: np.array([getattr(s, name) for s in samples])
            for name in ("q", "qd", "q_ref", "qd_ref", "tau", "tau_fb")
        },
    }
    events = [{"seq": 1, "t_ns": 1_000_000_000, "kind": "activated", "cycle": 0, "detail": ""}]
    assert (
        save_mcap_record(path, arrays, JOINTS, "arm", events=events, documents={"config": {"a": 1}, "period_s": 1e-3})
        == 50
    )
    record = read_mcap_record(path)
    for name in ("q", "qd", "q_ref", "qd_ref", "tau", "tau_fb"):
        np.testing.assert_array_equal(record[name], arrays[name])
    np.testing.assert_allclose(record["t_s"], np.arange(50) * 1e-3)
    assert list(record["joints"]) == list(JOINTS)
    assert float(record["period_s"]) == 1e-3 and list(record["seq"]) == list(range(50))  # plot: cycles x period
    with path.open("rb") as stream:
        assert {a.name for a in mcap_reader.make_reader(stream).iter_attachments()} == {"config.json"}


@pytest.mark.parametrize(
    ("content", "reason"),
    [(b"", "not a readable MCAP record"), (b"PK\x03\x04 not mcap", "invalid magic"), (None, "not a readable")],
)
def test_unreadable_files_are_one_line(tmp_path: Path, content: bytes | None, reason: str) -> None:
    path = tmp_path / "bad.mcap"
    if content is None:  # a real record cut in half
        full = tmp_path / "full.mcap"
        sink = _sink(full)
        sink.start()
        for k in range(3000):
            sink.offer_state(_sample(k))
        sink.close()
        content = full.read_bytes()[: full.stat().st_size // 2]
    path.write_bytes(content)
    with pytest.raises(McapRecordError, match=reason) as info:
        read_mcap_record(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_record_paths_are_checked_before_the_run(tmp_path: Path) -> None:
    assert check_record_path(tmp_path / "a" / "run.mcap") == "mcap"
    assert check_record_path(tmp_path / "run.NPZ") == "npz"
    for bad, reason in ((tmp_path / "run.bag", "unknown record format '.bag'"), (tmp_path / "d.mcap", "directory")):
        (tmp_path / "d.mcap").mkdir(exist_ok=True)
        with pytest.raises(OutputError, match=reason):
            check_record_path(bad)
    (tmp_path / "file").write_text("")
    with pytest.raises(OutputError, match="not a directory"):
        check_record_path(tmp_path / "file" / "run.mcap")
