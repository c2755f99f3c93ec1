"""Runs as MCAP files with ROS 2 message types (docs/formats.md).

Channels (timestamps: the runtime's CLOCK_MONOTONIC in ns, as log time, publish time and the
JointState header stamps; the ``hil`` metadata record carries the offset to wall time):

| topic | schema | what |
|---|---|---|
| ``/joint_states`` | ``sensor_msgs/msg/JointState`` (ros2msg, cdr) | measured q [rad], q̇ [rad/s], applied τ [N·m] |
| ``/joint_reference`` | ``sensor_msgs/msg/JointState`` (ros2msg, cdr) | q_ref, q̇_ref, the law's τ_fb |
| ``/hil/cycle`` | ``hil/Cycle`` (jsonschema, json) | seq, fallback, compute_s per cycle |
| ``/hil/stats`` | ``hil/Stats`` (jsonschema, json) | the runtime's 1 Hz statistics |
| ``/hil/status`` | ``hil/Status`` (jsonschema, json) | lifecycle state, fault, bundle id |
| ``/hil/events`` | ``hil/Event`` (jsonschema, json) | kind, cycle, detail |

Attachments: the robot's URDF (``<name>.urdf``, application/xml) and the bundle's
``manifest.json``; metadata ``hil`` (robot, joints, period, clock) and, at the end, ``recording``
(samples written, dropped).

:class:`McapRecorder` writes (one thread); :class:`McapSink` is a telemetry sink for ``hil run
--record x.mcap``: the loop only copies into a bounded deque (drops counted), a writer thread
encodes and writes. :func:`read_mcap_record` reads a file back into plot columns.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import struct
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drivers.draining import DrainingWriter
from hil_runtime.formats.ros2 import JOINT_STATE, JOINT_STATE_DEFINITION, JointStateEncoder, decode_joint_state
from hil_runtime.telemetry.sink import CycleState

log = logging.getLogger(__name__)

JOINT_STATES_TOPIC = "/joint_states"
REFERENCE_TOPIC = "/joint_reference"
CYCLE_TOPIC = "/hil/cycle"
STATS_TOPIC = "/hil/stats"
STATUS_TOPIC = "/hil/status"
EVENTS_TOPIC = "/hil/events"

_NUMBER = {"type": ["number", "null"]}
JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    "hil/Cycle": {
        "type": "object",
        "properties": {
            "seq": {"type": "integer", "description": "the loop's cycle number"},
            "fallback": {"type": "number", "description": "trust-region fallback, 0 (LMPC) .. 1 (law alone)"},
            "compute_s": {"type": "number", "description": "the cycle's loop work [s]"},
        },
        "required": ["seq", "fallback", "compute_s"],
    },
    "hil/Stats": {
        "type": "object",
        "description": "the runtime's statistics (docs/telemetry.md, stats); units in the names",
        "additionalProperties": _NUMBER,
    },
    "hil/Status": {
        "type": "object",
        "properties": {
            "state": {"type": "string"},
            "fault": {"type": ["string", "null"]},
            "bundle_id": {"type": ["string", "null"]},
        },
        "required": ["state"],
    },
    "hil/Event": {
        "type": "object",
        "properties": {"kind": {"type": "string"}, "cycle": {"type": "integer"}, "detail": {"type": "string"}},
        "required": ["kind", "cycle", "detail"],
    },
}


class McapRecordError(ValueError):
    """A file that is not a readable hil MCAP record, or mcap missing; one line, exit code 2."""

    exit_code = 2


def _writer_class() -> Any:
    try:
        from mcap.writer import Writer
    except ImportError:
        raise McapRecordError("MCAP recording needs the mcap package: pip install 'hil-runtime[formats]'") from None
    return Writer


def _json(document: Any) -> bytes:
    return json.dumps(document, separators=(",", ":"), allow_nan=False, default=_jsonable).encode()


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON: {type(value).__name__}")


def _finite_or_none(value: Any) -> float | None:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if np.isfinite(number) else None


class McapRecorder:
    """An MCAP file being written; not thread-safe (one writer). Written under a temporary name and
    renamed into place by :meth:`close`, so a reader never sees a file without its summary."""

    def __init__(
        self,
        path: Path | str,
        joints: Sequence[str],
        robot: str,
        *,
        urdf: tuple[str, bytes] | None = None,
        manifest: bytes | None = None,
        metadata: Mapping[str, str] | None = None,
    ) -> None:
        self.path = Path(path)
        self.joints = tuple(joints)
        self._tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.partial")
        self._file = open(self._tmp, "wb")  # noqa: SIM115 - closed by close(), which renames it into place
        self._writer = _writer_class()(self._file)
        self._writer.start(profile="ros2", library="hil-runtime")
        self._encoder = JointStateEncoder(self.joints)
        joint_state = self._writer.register_schema(
            name=JOINT_STATE, encoding="ros2msg", data=JOINT_STATE_DEFINITION.encode()
        )
        self._channels = {
            JOINT_STATES_TOPIC: self._writer.register_channel(JOINT_STATES_TOPIC, "cdr", joint_state),
            REFERENCE_TOPIC: self._writer.register_channel(REFERENCE_TOPIC, "cdr", joint_state),
        }
        for topic, schema_name in (
            (CYCLE_TOPIC, "hil/Cycle"),
            (STATS_TOPIC, "hil/Stats"),
            (STATUS_TOPIC, "hil/Status"),
            (EVENTS_TOPIC, "hil/Event"),
        ):
            schema = self._writer.register_schema(
                name=schema_name, encoding="jsonschema", data=_json(JSON_SCHEMAS[schema_name])
            )
            self._channels[topic] = self._writer.register_channel(topic, "json", schema)
        self._sequence = dict.fromkeys(self._channels, 0)
        now_ns = time.time_ns()
        if urdf is not None:
            self._writer.add_attachment(now_ns, now_ns, urdf[0], "application/xml", urdf[1])
        if manifest is not None:
            self._writer.add_attachment(now_ns, now_ns, "manifest.json", "application/json", manifest)
        offset_ns = time.clock_gettime_ns(time.CLOCK_REALTIME) - time.monotonic_ns()
        self._writer.add_metadata(
            "hil",
            {
                "robot": robot,
                "joints": json.dumps(list(self.joints)),
                "clock": "CLOCK_MONOTONIC of the runtime, ns",
                "realtime_minus_monotonic_ns": str(offset_ns),
                **(metadata or {}),
            },
        )
        self.states_written = 0

    def _add(self, topic: str, t_ns: int, data: bytes) -> None:
        sequence = self._sequence[topic] = self._sequence[topic] + 1
        self._writer.add_message(self._channels[topic], log_time=t_ns, data=data, publish_time=t_ns, sequence=sequence)

    def write_state(
        self,
        t_ns: int,
        seq: int,
        block: np.ndarray,
        fallback: float,
        compute_s: float,
    ) -> None:
        """One cycle; ``block`` is (6, N): q, qd, q_ref, qd_ref, tau, tau_fb."""
        q, qd, q_ref, qd_ref, tau, tau_fb = block
        encode = self._encoder.encode
        self._add(JOINT_STATES_TOPIC, t_ns, encode(t_ns, q, qd, tau))
        self._add(REFERENCE_TOPIC, t_ns, encode(t_ns, q_ref, qd_ref, tau_fb))
        self._add(CYCLE_TOPIC, t_ns, b'{"seq":%d,"fallback":%r,"compute_s":%r}' % (seq, fallback, compute_s))
        self.states_written += 1

    def write_stats(self, t_ns: int, stats: Mapping[str, Any]) -> None:
        self._add(STATS_TOPIC, t_ns, _json({name: _finite_or_none(value) for name, value in stats.items()}))

    def write_status(self, t_ns: int, status: Mapping[str, Any]) -> None:
        self._add(STATUS_TOPIC, t_ns, _json(dict(status)))

    def write_event(self, t_ns: int, event: Mapping[str, Any]) -> None:
        self._add(EVENTS_TOPIC, t_ns, _json(dict(event)))

    def add_metadata(self, name: str, values: Mapping[str, str]) -> None:
        self._writer.add_metadata(name, dict(values))

    def close(self) -> None:
        """Finish (summary, indexes) and rename into place."""
        if self._file.closed:
            return
        try:
            self._writer.finish()
        finally:
            self._file.close()
        os.replace(self._tmp, self.path)

    def abandon(self) -> None:
        """Drop the temporary file (an error before anything worth keeping)."""
        if not self._file.closed:
            self._file.close()
        self._tmp.unlink(missing_ok=True)


class McapSink(DrainingWriter):
    """A :class:`~hil_runtime.telemetry.sink.TelemetrySink` recording into an MCAP file.

    The loop's side is a copy into a bounded deque (``queue_size`` cycles); a full deque drops the
    new sample and counts it (``dropped``). A writer thread drains every ``drain_period_s``.
    """

    def __init__(self, recorder: McapRecorder, queue_size: int = 8192, drain_period_s: float = 0.01) -> None:
        super().__init__(drain_period_s, "hil-mcap", "MCAP recording")
        self.recorder = recorder
        self.queue_size = queue_size
        self.dropped = 0
        self.offered = 0
        self._states: collections.deque[tuple[int, int, np.ndarray, float, float]] = collections.deque()
        self._other: collections.deque[tuple[str, int, dict[str, Any]]] = collections.deque(maxlen=4096)
        self._bundle_id: str | None = None

    def start(self) -> None:
        self._start_draining()

    def offer_state(self, sample: CycleState) -> None:
        self.offered += 1
        if len(self._states) >= self.queue_size:
            self.dropped += 1
            return
        block = np.concatenate((sample.q, sample.qd, sample.q_ref, sample.qd_ref, sample.tau, sample.tau_fb))
        self._states.append((sample.t_ns, sample.seq, block, sample.fallback, sample.compute_s))

    def offer_stats(self, stats: Mapping[str, float]) -> None:
        self._other.append(("stats", time.monotonic_ns(), dict(stats)))

    def set_status(self, state: str, fault: str | None) -> None:
        self._other.append(("status", time.monotonic_ns(), {"state": state, "fault": fault}))

    def event(self, kind: str, cycle: int, detail: str) -> None:
        self._other.append(("event", time.monotonic_ns(), {"kind": kind, "cycle": int(cycle), "detail": detail}))

    def _drain(self) -> None:
        recorder = self.recorder
        n = len(recorder.joints)
        states = self._states
        while states:
            t_ns, seq, block, fallback, compute_s = states.popleft()
            recorder.write_state(t_ns, seq, block.reshape(6, n), fallback, compute_s)
        other = self._other
        while other:
            kind, t_ns, body = other.popleft()
            if kind == "stats":
                recorder.write_stats(t_ns, body)
            elif kind == "status":
                recorder.write_status(t_ns, body)
            else:
                recorder.write_event(t_ns, body)

    def close(self) -> None:
        """Stop the writer thread, write what is queued, finish the file (none if never started:
        a refused start-up leaves no recording)."""
        if not self._stop_draining():
            self.recorder.abandon()
            return
        self.recorder.add_metadata(
            "recording",
            {"states_written": str(self.recorder.states_written), "dropped": str(self.dropped)},
        )
        self.recorder.close()


def mcap_sink_for_run(
    path: Path, robot: str, joints: Sequence[str], bundle: Any, period_s: float, urdf: Path | None = None
) -> McapSink:
    """The ``hil run --record x.mcap`` sink: the bundle's manifest and its robot's URDF attached
    (found by :func:`hil_runtime.formats.urdf.find_urdf`, sha256-checked; ``urdf`` given explicitly
    first), the period in the ``hil`` metadata."""
    from hil_runtime.formats.urdf import find_urdf

    bundle_dir = Path(bundle.path)
    robot_doc = bundle.manifest.robot.model_dump()
    found = find_urdf(robot_doc.get("urdf_file", f"{robot}.urdf"), robot_doc.get("urdf_sha256"), bundle_dir, urdf)
    manifest_path = bundle_dir / "manifest.json"
    recorder = McapRecorder(
        path,
        joints,
        robot,
        urdf=(found.name, found.read_bytes()) if found is not None else None,
        manifest=manifest_path.read_bytes() if manifest_path.is_file() else None,
        metadata={"period_s": repr(float(period_s)), "law": str(getattr(bundle, "law_name", ""))},
    )
    if found is None:
        log.warning("MCAP record: no URDF matching the bundle's robot.urdf_sha256 found; none attached")
    return McapSink(recorder)


def urdf_of_bundle_document(
    bundle_doc: Mapping[str, Any] | None, robot: str, explicit: Path | None = None
) -> Path | None:
    """The URDF for a runtime known only by its telemetry (the ``bundle`` queryable): the manifest
    at the bundle's path when this machine can read it (sha256-checked), else ``<robot>.urdf``."""
    from hil_runtime.formats.urdf import find_urdf

    bundle_dir = Path(str((bundle_doc or {}).get("path", ""))) if (bundle_doc or {}).get("path") else None
    urdf_file, sha256 = f"{robot}.urdf", None
    if bundle_dir is not None:
        try:
            robot_doc = json.loads((bundle_dir / "manifest.json").read_text()).get("robot", {})
            urdf_file, sha256 = robot_doc.get("urdf_file", urdf_file), robot_doc.get("urdf_sha256")
        except (OSError, ValueError, AttributeError):
            bundle_dir = None
    return find_urdf(urdf_file, sha256, bundle_dir, explicit)


def save_mcap_record(
    path: Path,
    arrays: Mapping[str, np.ndarray],
    joints: Sequence[str],
    robot: str,
    status: Sequence[Mapping[str, Any]] = (),
    events: Sequence[Mapping[str, Any]] = (),
    documents: Mapping[str, Any] | None = None,
    urdf: Path | None = None,
    stats: Sequence[Mapping[str, Any]] = (),
) -> int:
    """``hil telemetry record --out x.mcap``: received state rows (``seq``, ``t_ns``, q, qd, q_ref,
    qd_ref, tau, tau_fb, fallback, compute_s), status, events and stats (each with its ``t_ns``) and JSON
    documents (config, bundle: attachments) into one MCAP file; returns the rows written."""
    attachments = {
        f"{name}.json": _json(doc) for name, doc in (documents or {}).items() if isinstance(doc, (dict, list))
    }
    period_s = (documents or {}).get("period_s")
    recorder = McapRecorder(
        path,
        joints,
        robot,
        urdf=(urdf.name, urdf.read_bytes()) if urdf is not None else None,
        metadata={"period_s": repr(float(period_s))} if isinstance(period_s, (int, float)) else None,
    )
    try:
        for name, data in attachments.items():
            now_ns = time.time_ns()
            recorder._writer.add_attachment(now_ns, now_ns, name, "application/json", data)
        block = np.stack([arrays[name] for name in ("q", "qd", "q_ref", "qd_ref", "tau", "tau_fb")], axis=1)
        for i in range(len(arrays["seq"])):
            recorder.write_state(
                int(arrays["t_ns"][i]),
                int(arrays["seq"][i]),
                block[i],
                float(arrays["fallback"][i]),
                float(arrays["compute_s"][i]),
            )
        for item in status:
            body = {k: v for k, v in item.items() if k not in ("seq", "t_ns")}
            recorder.write_status(int(item["t_ns"]), body)
        for item in events:
            recorder.write_event(int(item["t_ns"]), {k: v for k, v in item.items() if k not in ("seq", "t_ns")})
        for item in stats:
            recorder.write_stats(int(item["t_ns"]), {k: v for k, v in item.items() if k != "t_ns"})
        recorder.close()
    except BaseException:
        recorder.abandon()
        raise
    return recorder.states_written


def read_mcap_record(path: Path) -> dict[str, Any]:
    """Plot columns from an MCAP record (q, qd, tau, q_ref, qd_ref, tau_fb: (M, N); t_s; joints;
    fallback, compute_s when present). McapRecordError (one line) when it cannot be read."""
    try:
        from mcap.exceptions import McapError
        from mcap.reader import make_reader
    except ImportError:
        raise McapRecordError(f"{path}: reading MCAP needs the mcap package: pip install mcap") from None
    columns: dict[str, list[Any]] = {name: [] for name in ("t_ns", "q", "qd", "tau", "q_ref", "qd_ref", "tau_fb")}
    joints: list[str] = []
    seq: list[int] = []
    metadata: dict[str, str] = {}
    try:
        with open(path, "rb") as stream:
            reader = make_reader(stream)
            for record_metadata in reader.iter_metadata():
                if record_metadata.name == "hil":
                    metadata = dict(record_metadata.metadata)
            topics = [JOINT_STATES_TOPIC, REFERENCE_TOPIC, CYCLE_TOPIC]
            for _schema, channel, message in reader.iter_messages(topics=topics, log_time_order=True):
                if channel.topic == CYCLE_TOPIC:
                    seq.append(int(json.loads(message.data)["seq"]))
                    continue
                decoded = decode_joint_state(message.data)
                if channel.topic == JOINT_STATES_TOPIC:
                    joints = joints or decoded["name"]
                    columns["t_ns"].append(message.log_time)
                    for name, key in (("q", "position"), ("qd", "velocity"), ("tau", "effort")):
                        columns[name].append(decoded[key])
                else:
                    for name, key in (("q_ref", "position"), ("qd_ref", "velocity"), ("tau_fb", "effort")):
                        columns[name].append(decoded[key])
    except FileNotFoundError:
        raise McapRecordError(f"{path}: no such file") from None
    except (McapError, ValueError, EOFError, OSError, KeyError, TypeError, struct.error) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise McapRecordError(f"{path}: not a readable MCAP record ({reason})") from None
    if not columns["t_ns"]:
        raise McapRecordError(f"{path}: the record holds no {JOINT_STATES_TOPIC} messages")
    if len(columns["q_ref"]) != len(columns["q"]):
        raise McapRecordError(
            f"{path}: {len(columns['q'])} {JOINT_STATES_TOPIC} but {len(columns['q_ref'])} {REFERENCE_TOPIC} messages"
        )
    record: dict[str, Any] = {name: np.vstack(values) for name, values in columns.items() if name != "t_ns"}
    t_ns = np.asarray(columns["t_ns"], dtype=np.int64)
    record["t_s"] = (t_ns - t_ns[0]) * 1e-9
    record["joints"] = np.asarray(joints)
    # Cycles x period when both are known: a lock-stepped run's wall time is not its time (plot.py).
    period_s = _finite_or_none(metadata.get("period_s"))
    if period_s is not None and period_s > 0 and len(seq) == len(t_ns):
        record["seq"] = np.asarray(seq, dtype=np.int64)
        record["period_s"] = np.asarray(period_s)
    return record
