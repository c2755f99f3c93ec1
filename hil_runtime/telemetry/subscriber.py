"""The subscriber side: a Zenoh session to one runtime's ``hil/<robot>/`` (docs/telemetry.md).

    client = TelemetryClient.open(connect=["tcp/127.0.0.1:7447"], robot=None)  # None: the one alive
    schema = client.schema()                     # queried, then every payload decodes against it
    client.subscribe("state", lambda payload: ...)
    rec = record_state(client, schema, seconds=10.0)
    save_record(rec, Path("run.npz"))

Used by ``hil telemetry`` and the tests. The session is a peer that listens nowhere and connects
only to the named endpoints (no multicast or gossip scouting): nothing leaves those addresses.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

import numpy as np

from hil_runtime.telemetry.codec import HEADER_SIZE, Schema, TelemetryDecodeError
from hil_runtime.telemetry.config import (
    DEFAULT_LISTEN,
    KEY_PREFIX,
    TelemetryConfigError,
    check_key_chunk,
    zenoh_config,
    zenoh_reason,
)

QUERYABLES = ("schema", "config", "bundle")
CONTROLS = ("stop", "reset")
UNKNOWN_SOURCE = "unknown"  # a sample without Zenoh source info (the runtime's always carry it)


class TelemetryUnavailable(RuntimeError):
    """No runtime answered (wrong endpoint or robot, telemetry disabled); one line, exit code 1."""

    exit_code = 1


class TelemetryClient:
    """One subscriber session to one robot's telemetry."""

    def __init__(self, session: Any, robot: str, timeout_s: float) -> None:
        self.session = session
        self.robot = robot
        self.prefix = f"{KEY_PREFIX}/{robot}"
        self.timeout_s = timeout_s
        self._declared: list[Any] = []
        # Samples received per publishing session (Zenoh id from the source info): more than one
        # session publishing as hil/<robot> is another runtime of that name, or an impersonator.
        self.publishers: dict[str, int] = {}

    @classmethod
    def open(
        cls,
        connect: Sequence[str] = (DEFAULT_LISTEN,),
        robot: str | None = None,
        timeout_s: float = 3.0,
        config_file: Path | None = None,
    ) -> TelemetryClient:
        import zenoh

        conf = zenoh_config("peer", [], list(connect), config_file)
        # Zenoh retries a refused connect after 1 s, then 2, 4 s: a subscriber started just before
        # the runtime would miss its first seconds. Retry every 100-500 ms instead.
        conf.insert_json5(
            "connect/retry", '{"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 1.5}'
        )
        try:
            session = zenoh.open(conf)
        except zenoh.ZError as exc:
            raise TelemetryUnavailable(
                f"cannot open a Zenoh session to {', '.join(connect)}: {zenoh_reason(exc)}"
            ) from None
        try:
            if robot is None:
                robot = _single_robot(session, connect, timeout_s)
            else:
                check_key_chunk(robot, "--robot")
        except BaseException:
            session.close()  # type: ignore[no-untyped-call]  # zenoh's stub leaves Session.close unannotated
            raise
        return cls(session, robot, timeout_s)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def close(self, timeout_s: float = 1.0) -> None:
        """Undeclare and close; waits at most ``timeout_s`` for Zenoh (a runtime that hangs, e.g.
        SIGSTOP, keeps its session close busy up to 10 s: that finishes on a helper thread)."""
        for entity in self._declared:
            try:
                entity.undeclare()
            except Exception:  # noqa: BLE001, S110 - closing: nothing useful to do with it
                pass
        self._declared.clear()
        closer = threading.Thread(target=_close_session, args=(self.session,), name="telemetry-client-close")
        closer.start()  # not a daemon: a daemon thread still inside Zenoh aborts the interpreter at exit
        closer.join(timeout_s)

    # --- queries ---------------------------------------------------------------------------------

    def query(self, name: str, timeout_s: float | None = None) -> bytes:
        """The reply of ``hil/<robot>/<name>`` (schema, config, bundle, or a control)."""
        key = f"{self.prefix}/{name}"
        deadline_s = self.timeout_s if timeout_s is None else timeout_s
        # A freshly opened session may not have its route to the runtime yet: retry until the deadline.
        end = time.monotonic() + deadline_s
        while True:
            remaining = max(0.1, end - time.monotonic())
            for reply in self.session.get(key, timeout=min(remaining, 1.0)):
                if reply.ok is not None:
                    payload: bytes = reply.ok.payload.to_bytes()
                    return payload
                raise TelemetryUnavailable(f"{key}: the runtime replied with an error: {reply.err.payload.to_string()}")
            if time.monotonic() >= end:
                raise TelemetryUnavailable(
                    f"no reply from {key} within {deadline_s:g} s (runtime not running, telemetry disabled, "
                    "another --robot or --connect endpoint?)"
                )
            time.sleep(0.05)

    def query_json(self, name: str, timeout_s: float | None = None) -> Any:
        payload = self.query(name, timeout_s)
        try:
            return json.loads(payload)
        except (json.JSONDecodeError, UnicodeDecodeError):
            raise TelemetryUnavailable(f"{self.prefix}/{name}: the reply is not JSON") from None

    def schema(self) -> Schema:
        return Schema.from_json(self.query("schema"))

    # --- subscriptions (callbacks run on Zenoh's threads) ----------------------------------------

    def subscribe(self, name: str, callback: Callable[[bytes], None]) -> None:
        """Payload bytes of ``hil/<robot>/<name>`` (state, stats, status, events); the publishing
        session of each sample is counted in :attr:`publishers`."""
        publishers = self.publishers

        def on_sample(sample: Any) -> None:
            info = sample.source_info
            source = str(info.source_id.zid) if info is not None else UNKNOWN_SOURCE
            publishers[source] = publishers.get(source, 0) + 1
            callback(sample.payload.to_bytes())

        self._declared.append(self.session.declare_subscriber(f"{self.prefix}/{name}", on_sample))

    def schema_repliers(self, timeout_s: float = 1.0) -> list[str]:
        """The Zenoh ids of every session answering ``hil/<robot>/schema`` (all of them, not the first)."""
        import zenoh

        repliers: set[str] = set()
        replies = self.session.get(
            f"{self.prefix}/schema",
            timeout=timeout_s,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
        )
        for reply in replies:
            if reply.ok is not None:
                replier = reply.replier_id
                repliers.add(str(replier.zid) if replier is not None else UNKNOWN_SOURCE)
        return sorted(repliers)

    def impersonation_warning(self, repliers: Sequence[str] = ()) -> str | None:
        """One line when more than one session publishes as (or answers for) this robot."""
        return impersonation_warning(self.prefix, self.publishers, repliers)

    def watch_alive(self, callback: Callable[[bool], None]) -> None:
        """``callback(True)`` when the runtime's liveliness token appears (or already exists),
        ``callback(False)`` when it goes: a clean close, or the session's lease running out."""
        import zenoh

        def on_sample(sample: Any) -> None:
            callback(sample.kind == zenoh.SampleKind.PUT)

        self._declared.append(
            self.session.liveliness().declare_subscriber(f"{self.prefix}/alive", on_sample, history=True)
        )


def impersonation_warning(prefix: str, publishers: Iterable[str], repliers: Iterable[str]) -> str | None:
    """Several sessions among the samples' sources (``unknown``: a sample without source info,
    never the runtime's) or among the schema's repliers: one line naming them, else None."""
    samples, answers = sorted(set(publishers)), sorted(set(repliers))
    if len(samples) <= 1 and len(answers) <= 1 and (not samples or not answers or samples == answers):
        return None
    return (
        f"warning: several Zenoh sessions publish as {prefix} (samples from {', '.join(samples) or '-'}; "
        f"schema from {', '.join(answers) or '-'}): another runtime with this robot name, or an impersonator "
        "(docs/security.md)"
    )


def _close_session(session: Any) -> None:
    try:
        session.close()
    except Exception:  # noqa: BLE001, S110 - e.g. "close operation timed out": the peer is gone anyway
        pass


def _single_robot(session: Any, connect: Sequence[str], timeout_s: float) -> str:
    """The robot whose ``hil/*/alive`` token is seen; refuses none or several (give --robot)."""
    end = time.monotonic() + timeout_s
    robots: set[str] = set()
    while not robots:
        for reply in session.liveliness().get(f"{KEY_PREFIX}/*/alive", timeout=min(1.0, timeout_s)):
            if reply.ok is not None:
                robots.add(str(reply.ok.key_expr).split("/")[1])
        if robots or time.monotonic() >= end:
            break
        time.sleep(0.1)
    if not robots:
        raise TelemetryUnavailable(
            f"no runtime alive at {', '.join(connect)} within {timeout_s:g} s (is 'hil run' up with telemetry enabled?)"
        )
    if len(robots) > 1:
        raise TelemetryConfigError(f"several robots alive ({', '.join(sorted(robots))}): choose one with --robot")
    return robots.pop()


# --- recording --------------------------------------------------------------------------------------


@dataclass
class StateRecording:
    """Raw payloads received, decoded once at the end against ``schema`` (the callbacks only
    append, and can start before the schema is known, so nothing is missed while it is queried)."""

    schema: Schema | None = None
    payloads: list[bytes] = field(default_factory=list)
    status_payloads: list[bytes] = field(default_factory=list)
    event_payloads: list[bytes] = field(default_factory=list)
    refused: int = 0
    first_refusal: str = ""

    def _schema(self) -> Schema:
        if self.schema is None:
            raise TelemetryUnavailable("the recording has no schema to decode against")
        return self.schema

    def _json(
        self, payloads: list[bytes], decode: Callable[[bytes], tuple[Any, dict[str, Any]]]
    ) -> list[dict[str, Any]]:
        out: list[dict[str, Any]] = []
        for payload in list(payloads):
            try:
                header, body = decode(payload)
            except TelemetryDecodeError as exc:
                self.refused += 1
                self.first_refusal = self.first_refusal or str(exc)
                continue
            if not header.warmup:
                out.append({"seq": header.seq, "t_ns": header.t_ns, **body})
        return out

    @property
    def status(self) -> list[dict[str, Any]]:
        return self._json(self.status_payloads, self._schema().decode_status)

    @property
    def events(self) -> list[dict[str, Any]]:
        return self._json(self.event_payloads, self._schema().decode_event)

    def arrays(self) -> dict[str, np.ndarray]:
        """Columns per field (q: (M, N), fallback: (M,), ...), seq, t_ns, flags, t_s from the first sample."""
        schema = self._schema()
        rows: list[np.ndarray] = []
        seq: list[int] = []
        t_ns: list[int] = []
        flags: list[int] = []
        for payload in list(self.payloads):
            try:
                header, body = schema.decode_state_row(payload)
            except TelemetryDecodeError as exc:
                self.refused += 1
                self.first_refusal = self.first_refusal or str(exc)
                continue
            if header.warmup:
                continue
            rows.append(body)
            seq.append(header.seq)
            t_ns.append(header.t_ns)
            flags.append(header.flags)
        width = (schema.state_size - HEADER_SIZE) // 8
        body_rows = np.vstack(rows) if rows else np.zeros((0, width))
        out: dict[str, np.ndarray] = {
            "seq": np.asarray(seq, dtype=np.uint64),
            "t_ns": np.asarray(t_ns, dtype=np.int64),
            "flags": np.asarray(flags, dtype=np.uint8),
        }
        out["t_s"] = (out["t_ns"] - out["t_ns"][0]) * 1e-9 if len(t_ns) else np.zeros(0)
        for name, start, count in schema.body_columns():
            column = body_rows[:, start : start + count]
            out[name] = column[:, 0].copy() if name in ("fallback", "compute_s") else column.copy()
        return out


def start_recording(client: TelemetryClient) -> StateRecording:
    """Subscribe to state, status and events now; set ``schema`` before decoding."""
    recording = StateRecording()
    # list.append is atomic under the GIL: no lock on Zenoh's receive thread.
    client.subscribe("state", recording.payloads.append)
    client.subscribe("status", recording.status_payloads.append)
    client.subscribe("events", recording.event_payloads.append)
    return recording


def record_state(
    client: TelemetryClient, schema: Schema, seconds: float, stop: threading.Event | None = None
) -> StateRecording:
    """Collect ``hil/<robot>/state`` (and status, events) for ``seconds`` of wall time."""
    recording = start_recording(client)
    recording.schema = schema
    (stop or threading.Event()).wait(seconds)
    return recording


def save_record(recording: StateRecording, path: Path, extra: dict[str, Any] | None = None) -> int:
    """Write an npz (atomically): the state columns, ``joints``, ``schema`` (the JSON it was decoded
    against), ``status``/``events`` (JSON lines), and ``extra`` JSON documents (config, bundle)."""
    from hil_runtime.outputs import atomic_path

    arrays = recording.arrays()
    schema = recording._schema()
    documents = {
        "joints": np.asarray(schema.joints),
        "robot": np.asarray(schema.robot),
        "schema": np.asarray(json.dumps(schema.document)),
        "status": np.asarray("\n".join(json.dumps(item) for item in recording.status)),
        "events": np.asarray("\n".join(json.dumps(item) for item in recording.events)),
    }
    for name, document in (extra or {}).items():
        documents[name] = np.asarray(document if isinstance(document, float) else json.dumps(document))
    # Any values: numpy's stub types savez_compressed's **kwds as also reaching its bool allow_pickle.
    named: dict[str, Any] = {**arrays, **documents}
    with atomic_path(path) as tmp:
        np.savez_compressed(tmp, **named)
    return len(arrays["seq"])


def missing_samples(seq: np.ndarray, stride: int = 1) -> int:
    """Samples lost between the first and last received (by sequence number, decimation ``stride``)."""
    if len(seq) < 2:
        return 0
    expected = int((int(seq.max()) - int(seq.min())) // stride) + 1
    return expected - len(np.unique(seq))
