"""``hil telemetry watch``'s state (attach_watch): every key's payloads decoded, WARMUP puts
skipped, refused payloads counted with the reason, liveliness changes timed."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hil_runtime.telemetry.cli import attach_watch
from hil_runtime.telemetry.codec import (
    FLAG_GAP,
    FLAG_WARMUP,
    Kind,
    Schema,
    build_schema,
    encode_header,
    encode_json,
    encode_state,
    encode_stats,
)

JOINTS = ("a", "b")


class _Client:
    def __init__(self) -> None:
        self.handlers: dict[str, Callable[[bytes], None]] = {}
        self.alive: Callable[[bool], None] | None = None
        self.publishers: dict[str, int] = {}
        self.repliers: list[str] = []

    def schema_repliers(self) -> list[str]:
        return self.repliers

    def subscribe(self, key: str, handler: Callable[[bytes], None]) -> None:
        self.handlers[key] = handler

    def watch_alive(self, handler: Callable[[bool], None]) -> None:
        self.alive = handler


def test_each_key_is_decoded_warmup_skipped_and_refusals_counted() -> None:
    client = _Client()
    schema = Schema(build_schema("arm", JOINTS))
    state = attach_watch(client, schema)
    assert set(client.handlers) == {"state", "stats", "status", "events"}

    for key, kind in (("state", Kind.STATE), ("stats", Kind.STATS), ("status", Kind.STATUS), ("events", Kind.EVENT)):
        client.handlers[key](encode_header(kind, 0, 0, FLAG_WARMUP))
    assert state.sample is None and state.stats == {} and state.status == {} and not state.events
    assert state.refused == 0

    blocks = [np.full(2, float(b)) for b in range(6)]
    client.handlers["state"](encode_state(5, 10, blocks, 1.0, 2e-6, flags=FLAG_GAP))
    assert state.sample is not None
    assert state.sample.header.seq == 5 and state.gaps == 1 and len(state.arrivals) == 1
    np.testing.assert_array_equal(state.sample["tau_fb"], blocks[5])
    assert state.arrivals[0][1] is True  # fallback > 0

    client.handlers["stats"](encode_stats(1, 0, {"rate_hz": 999.0}))
    assert state.stats["rate_hz"] == 999.0
    client.handlers["status"](encode_json(Kind.STATUS, 1, 0, {"state": "ACTIVE", "fault": None, "bundle_id": "x"}))
    assert state.status["state"] == "ACTIVE"
    client.handlers["events"](encode_json(Kind.EVENT, 1, 0, {"kind": "fault", "cycle": 7, "detail": "why"}))
    assert state.events[-1].endswith("cycle 7: fault why")

    client.handlers["stats"](b"garbage")
    client.handlers["state"](encode_header(Kind.STATS, 1, 0))  # a header of the wrong kind
    assert state.refused == 2 and state.last_refusal
    assert state.sample is not None and state.sample.header.seq == 5  # what was refused replaced nothing

    assert client.alive is not None
    client.alive(True)
    assert state.alive is True
    client.alive(False)
    assert state.alive is False


def _text(renderable: object) -> str:
    from rich.console import Console

    console = Console(width=200, record=True, file=open("/dev/null", "w"))  # noqa: SIM115 - closed with the console
    console.print(renderable)
    return console.export_text()


def test_the_view_names_the_publishing_session_and_warns_when_several_publish() -> None:
    from hil_runtime.telemetry.cli import render_watch

    client = _Client()
    client.repliers = ["aaa1"]
    state = attach_watch(client, Schema(build_schema("arm", JOINTS)))
    client.publishers["aaa1"] = 10  # the client counts each sample's session; the view reads the same dict
    text = _text(render_watch(state, "arm", JOINTS))
    assert "published by Zenoh session aaa1" in text and "WARNING" not in text
    client.publishers["bbb2"] = 3  # a second session publishing as hil/arm
    text = _text(render_watch(state, "arm", JOINTS))
    assert "WARNING: several Zenoh sessions publish as hil/arm (samples from aaa1, bbb2; schema from aaa1)" in text
