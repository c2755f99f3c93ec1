"""The Zenoh telemetry sink: the loop copies, one publisher thread sends (docs/telemetry.md).

The loop thread only ever copies into a bounded deque:

- ``offer_state`` encodes the sample (one ``struct.pack`` for the header and the two scalars, one
  ``tobytes`` per joint block, one ``join``: about 2-4 µs on the loop thread, immutable bytes, so
  the publisher can never read a half-written sample) and appends it to a deque of
  ``queue_size``. It never waits: when the deque is full the append pushes the oldest sample out,
  counted as ``telemetry_dropped``; the next sample sent carries the GAP flag. (A preallocated
  ring written with ``pack_into`` + ``np.concatenate(out=)`` measured 1.2 µs hot but 6-15 µs
  at 1 kHz with cold caches, worse than this; see docs/telemetry.md.)
- ``event`` appends to a bounded deque (drop-oldest, counted); ``offer_stats`` and ``set_status``
  swap one reference.

One publisher thread wakes every ``publish_period_s``, sends what is pending with congestion
control DROP (a slow subscriber loses samples, the runtime never waits for it; Zenoh batches
them unless ``express``, see the config), and
republishes stats and status every ``stats_period_s``. The session, publishers (warmed up with
one WARMUP-flagged put each), liveliness token and queryables are all made in ``start()``, before
the loop goes ACTIVE.
"""

from __future__ import annotations

import collections
import json
import logging
import struct
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, Protocol, runtime_checkable

from hil_runtime.telemetry.codec import (
    FLAG_GAP,
    FLAG_WARMUP,
    STATS_FIELDS,
    Kind,
    build_schema,
    encode_header,
    encode_json,
    encode_state,
    encode_stats,
    state_size,
)
from hil_runtime.telemetry.config import TelemetryConfig, TelemetryConfigError, publisher_zenoh_config, zenoh_reason
from hil_runtime.telemetry.sink import CycleState

log = logging.getLogger(__name__)

_STATE = int(Kind.STATE)


@runtime_checkable
class TelemetryControls(Protocol):
    """What the stop/reset queryables call (from a Zenoh thread: must only set a request)."""

    def request_stop(self) -> None: ...

    def request_reset(self, activate: bool | None = None) -> None: ...


class TelemetryStartError(RuntimeError):
    """The Zenoh session could not be opened (port in use, bad json5 config...); one line."""

    exit_code = 2


class ZenohTelemetry:
    """A :class:`~hil_runtime.telemetry.sink.TelemetrySink` publishing under ``hil/<robot>/``.

    ``info``: ``joints`` (names, required: the state layout), ``config`` (config summary, served
    by the ``config`` queryable), ``bundle`` (manifest summary and hashes, served by ``bundle``;
    its ``bundle_id`` or ``id`` goes into status), optional ``stats_fields`` (extra stats names).
    """

    def __init__(
        self,
        config: TelemetryConfig,
        robot: str,
        info: Mapping[str, Any],
        controls: TelemetryControls | None = None,
    ) -> None:
        joints = info.get("joints")
        if not joints or not all(isinstance(name, str) for name in joints):
            raise TelemetryConfigError("telemetry: info['joints'] must list the joint names (the state layout)")
        self.config = config
        self.prefix = config.key_prefix(robot)
        self.robot = self.prefix.split("/", 1)[1]
        self.n_joints = len(joints)
        extra = tuple(info.get("stats_fields", ()))
        self.stats_fields = tuple(dict.fromkeys((*STATS_FIELDS, *extra)))
        self.schema = build_schema(self.robot, list(joints), self.stats_fields)
        bundle = dict(info.get("bundle") or {})
        self.bundle_id = str(info.get("bundle_id") or bundle.get("bundle_id") or bundle.get("id") or "")
        self._replies = {
            "schema": _json_bytes(self.schema),
            "config": _json_bytes({"telemetry": config.summary(), **dict(info.get("config") or {})}),
            "bundle": _json_bytes(bundle),
        }
        self._controls = controls

        # Encoded state payloads (immutable bytes) waiting for the publisher thread; drop-oldest.
        self._cap = config.queue_size
        self._row = state_size(self.n_joints)
        self._states: collections.deque[bytes] = collections.deque(maxlen=self._cap)
        self._offered = 0
        self._decimation = config.state_decimation
        self._skipped = 0

        self._events: collections.deque[tuple[int, str, int, str]] = collections.deque(maxlen=config.event_queue_size)
        self._events_dropped = 0
        self._stats: Mapping[str, float] = {}
        self._status: tuple[str, str | None] = ("UNCONFIGURED", None)
        self._status_version = 0
        self._last_seq = 0

        self.sent = 0
        self.dropped = 0
        self._dropped_seen = 0
        self.offer_errors = 0
        self.publish_errors = 0
        self.refused_controls = 0  # control queries for a key expression other than exactly theirs
        self._unknown_stats: set[str] = set()

        self._running = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._session: Any = None
        self._publishers: dict[str, Any] = {}
        self._declared: list[Any] = []
        self._token: Any = None
        self._source_info: Any = None
        self._source_ids: dict[str, Any] = {}
        self._source_sn: dict[str, int] = {}
        self._ros2: Any = None  # hil_runtime.formats.rmw_zenoh.JointStatePublisher when ros2.enabled
        self.joints = tuple(joints)

    # --- the loop's side ------------------------------------------------------------------------

    def start(self) -> None:
        import zenoh

        if self._running:
            return
        try:
            self._session = zenoh.open(publisher_zenoh_config(self.config))
        except zenoh.ZError as exc:
            endpoints = ", ".join(self.config.listen) or "-"
            raise TelemetryStartError(
                f"telemetry: cannot open the Zenoh session (listen {endpoints}): {zenoh_reason(exc)}"
            ) from None
        session = self._session
        for name in ("state", "stats", "status", "events"):
            self._publishers[name] = session.declare_publisher(
                f"{self.prefix}/{name}",
                congestion_control=zenoh.CongestionControl.DROP,
                priority=zenoh.Priority.DATA_HIGH if name == "state" else zenoh.Priority.DATA,
                express=self.config.express,
            )
        for name, payload in self._replies.items():
            self._declared.append(session.declare_queryable(f"{self.prefix}/{name}", self._replier(name, payload)))
        if self._controls is not None:
            controls = self._controls
            # A remote reset clears the FAULT only: the drives are enabled again by a local decision
            # (the control socket), unless the config says otherwise (docs/security.md, "Zenoh").
            activate = None if self.config.remote_reset_activates else False
            requests = (("stop", controls.request_stop), ("reset", lambda: controls.request_reset(activate=activate)))
            for name, request in requests:
                self._declared.append(session.declare_queryable(f"{self.prefix}/{name}", self._control(name, request)))
        # Every put carries this session's id (Zenoh's source info): subscribers show which session
        # publishes as hil/<robot> and warn when several do (an impersonator, docs/security.md).
        self._source_info = zenoh.SourceInfo
        self._source_ids = {name: publisher.id for name, publisher in self._publishers.items()}
        self._source_sn = dict.fromkeys(self._publishers, 0)
        # The first put on a new publisher is ~100x slower: pay it here, flagged so readers skip it.
        for name in self._publishers:
            self._put(name, encode_header(_KIND_OF[name], 0, time.monotonic_ns(), FLAG_WARMUP))
        self._token = session.liveliness().declare_token(f"{self.prefix}/alive")
        if self.config.ros2.enabled:  # ROS 2's /joint_states beside hil/<robot>/ (docs/formats.md)
            from hil_runtime.formats.rmw_zenoh import JointStatePublisher

            ros2 = self.config.ros2
            self._ros2 = JointStatePublisher(
                session,
                self.joints,
                ros2.domain_id,
                ros2.namespace,
                ros2.node,
                ros2.topic,
                ros2.frame_id,
                ros2.decimation,
            )
        self._stop.clear()
        self._running = True
        self._thread = threading.Thread(target=self._run, name=f"telemetry-{self.robot}", daemon=True)
        self._thread.start()

    def offer_state(self, sample: CycleState) -> None:
        self._last_seq = sample.seq
        if self._decimation > 1:
            self._skipped += 1
            if self._skipped < self._decimation:
                return
            self._skipped = 0
        states = self._states
        if len(states) == self._cap:
            self.dropped += 1  # append below pushes the oldest out
        s = sample
        try:
            states.append(
                encode_state(s.seq, s.t_ns, (s.q, s.qd, s.q_ref, s.qd_ref, s.tau, s.tau_fb), s.fallback, s.compute_s)
            )
        except (AttributeError, TypeError, ValueError, OverflowError, struct.error) as exc:
            # A caller bug (lists, negative seq) must not stop the arm: count it, say it once.
            self.offer_errors += 1
            if self.offer_errors == 1:
                log.error("telemetry: state sample refused (%s); further ones counted only", exc)
            return
        self._offered += 1

    def offer_stats(self, stats: Mapping[str, float]) -> None:
        self._stats = stats  # the publisher thread reads it once per stats period

    def set_status(self, state: str, fault: str | None) -> None:
        previous = self._status
        if (state, fault) == previous:
            return
        self._status = (state, fault)
        self._status_version += 1
        self.event("lifecycle", self._last_seq, f"{previous[0]} -> {state}" + (f": {fault}" if fault else ""))

    def event(self, kind: str, cycle: int, detail: str) -> None:
        if len(self._events) == self._events.maxlen:
            self._events_dropped += 1
        self._events.append((time.monotonic_ns(), kind, cycle, detail))

    def close(self) -> None:
        if not self._running:
            return
        self._running = False
        self._stop.set()
        if self._thread is not None:
            self._thread.join(self.config.close_timeout_s)
            if self._thread.is_alive():
                log.warning(
                    "telemetry: publisher thread still busy after %.1f s; closing anyway", self.config.close_timeout_s
                )
        if self._ros2 is not None:
            self._ros2.close()
            self._ros2 = None
        # Undeclare the token first: subscribers see the runtime leave at once, not by timeout.
        for entity in (self._token, *self._declared, *self._publishers.values()):
            try:
                if entity is not None:
                    entity.undeclare()
            except Exception as exc:  # noqa: BLE001 - closing must finish whatever Zenoh says
                log.debug("telemetry: undeclare failed: %s", exc)
        self._token = None
        self._declared.clear()
        self._publishers.clear()
        # Zenoh's close flushes every link and waits up to 10 s for a peer that stopped reading (a
        # stalled subscriber, until its lease runs out); the runtime's shutdown must not. Close on a
        # helper thread, wait at most close_timeout_s, and go on. Not a daemon thread: the
        # interpreter waits for it at exit (a daemon thread still inside Zenoh aborts the process).
        session, self._session = self._session, None
        closer = threading.Thread(target=_close_quietly, args=(session,), name="telemetry-close", daemon=False)
        closer.start()
        closer.join(self.config.close_timeout_s)
        if closer.is_alive():
            log.warning(
                "telemetry: Zenoh session still closing after %.1f s (a stalled peer); not waiting",
                self.config.close_timeout_s,
            )

    # --- counters -------------------------------------------------------------------------------

    @property
    def counters(self) -> dict[str, int]:
        return {
            "offered": self._offered,
            "sent": self.sent,
            "dropped": self.dropped,
            "events_dropped": self._events_dropped,
            "offer_errors": self.offer_errors,
            "publish_errors": self.publish_errors,
        }

    # --- the publisher thread -------------------------------------------------------------------

    def _run(self) -> None:
        period_s = self.config.publish_period_s
        stats_period_ns = int(self.config.stats_period_s * 1e9)
        next_stats_ns = time.monotonic_ns()
        status_sent = -1
        seq = {"stats": 0, "status": 0, "events": 0}
        while True:
            stopping = self._stop.wait(period_s)
            try:
                self._drain_state()
                while self._events:
                    t_ns, kind, cycle, detail = self._events.popleft()
                    seq["events"] += 1
                    body = {"kind": kind, "cycle": cycle, "detail": detail}
                    self._put("events", encode_json(Kind.EVENT, seq["events"], t_ns, body))
                now_ns = time.monotonic_ns()
                due = now_ns >= next_stats_ns
                if due or self._status_version != status_sent:
                    status_sent = self._status_version
                    state, fault = self._status
                    seq["status"] += 1
                    body = {"state": state, "fault": fault, "bundle_id": self.bundle_id}
                    self._put("status", encode_json(Kind.STATUS, seq["status"], now_ns, body))
                if due or stopping:
                    seq["stats"] += 1
                    self._put("stats", encode_stats(seq["stats"], now_ns, self._stats_values(), self.stats_fields))
                    # Skip missed periods rather than catching up in a burst.
                    next_stats_ns += stats_period_ns * max(1, (now_ns - next_stats_ns) // stats_period_ns + 1)
            except Exception as exc:  # noqa: BLE001 - the thread must survive anything Zenoh raises
                self.publish_errors += 1
                if self.publish_errors == 1:
                    log.error("telemetry: publishing failed (%s); further failures counted only", exc)
            if stopping:
                return

    def _drain_state(self) -> None:
        states, row = self._states, self._row
        while states:
            try:
                payload: bytes | bytearray = states.popleft()
            except IndexError:  # emptied under us (cannot happen with one reader; be safe)
                return
            if len(payload) != row:  # arrays of the wrong size or dtype: refuse, never send garbage
                self.offer_errors += 1
                if self.offer_errors == 1:
                    log.error("telemetry: state sample of %d bytes refused (the schema says %d)", len(payload), row)
                continue
            dropped = self.dropped
            if dropped != self._dropped_seen:  # samples were pushed out just before this one
                self._dropped_seen = dropped
                payload = bytearray(payload)
                payload[7] |= FLAG_GAP
            try:
                self._put("state", payload)
                self.sent += 1
                if self._ros2 is not None:
                    self._ros2.publish_state_payload(payload)
            except Exception as exc:  # noqa: BLE001 - Zenoh's errors are untyped; telemetry never stops the loop
                self.publish_errors += 1
                if self.publish_errors == 1:
                    log.error("telemetry: state put failed (%s); further failures counted only", exc)

    def _stats_values(self) -> dict[str, float]:
        values = dict(self._stats)
        unknown = set(values) - set(self.stats_fields) - self._unknown_stats
        if unknown:
            self._unknown_stats |= unknown
            log.warning("telemetry: stats not in the schema, not published: %s", ", ".join(sorted(unknown)))
        values["telemetry_sent"] = float(self.sent)
        values["telemetry_dropped"] = float(self.dropped)
        return values

    def _put(self, name: str, payload: bytes | bytearray) -> None:
        source_id = self._source_ids.get(name)
        if source_id is None:  # a publisher not declared by start() carries no source info
            self._publishers[name].put(payload)
            return
        sn = self._source_sn[name] = self._source_sn[name] + 1
        self._publishers[name].put(payload, source_info=self._source_info(source_id, sn))

    # --- queryables (run on Zenoh's threads) -----------------------------------------------------

    def _replier(self, name: str, payload: bytes) -> Callable[[Any], None]:
        key = f"{self.prefix}/{name}"

        def reply(query: Any) -> None:
            query.reply(key, payload)

        return reply

    def _control(self, name: str, request: Callable[[], None]) -> Callable[[Any], None]:
        key = f"{self.prefix}/{name}"

        def control(query: Any) -> None:
            # Zenoh hands a queryable every query whose key expression intersects its own:
            # hil/<robot>/**, hil/*/stop, hil/<robot>/re$*... Access-control rules match key
            # expressions too, so a wildcard can slip past a rule written for the exact key. A
            # control acts only on a query for exactly its key; anything else is refused, unanswered
            # by a success.
            asked = str(query.key_expr)
            if asked != key:
                self.refused_controls += 1
                log.warning("telemetry: %s refused: query for %r, not exactly %r", name, asked, key)
                query.reply_err(_json_bytes({"ok": False, "request": name, "error": f"only {key} itself"}))
                return
            try:
                request()
            except Exception as exc:  # noqa: BLE001 - report to the caller, keep the runtime going
                query.reply(key, _json_bytes({"ok": False, "request": name, "error": str(exc)}))
                return
            log.warning("telemetry: %s requested over Zenoh", name)
            query.reply(key, _json_bytes({"ok": True, "request": name}))

        return control


def _close_quietly(session: Any) -> None:
    try:
        session.close()
    except Exception as exc:  # noqa: BLE001 - nothing to do about it at shutdown
        log.debug("telemetry: session close: %s", exc)


_KIND_OF = {"state": Kind.STATE, "stats": Kind.STATS, "status": Kind.STATUS, "events": Kind.EVENT}


def _json_bytes(document: Any) -> bytes:
    return json.dumps(document, default=str, sort_keys=True).encode("utf-8")
