"""Telemetry over Zenoh on 127.0.0.1 (scouting off), against a fake 1 kHz loop.

- an independent subscriber process (``hil telemetry record``) receives >= 99.9 % of the state
  samples, decoded against the schema it queried, and the values are the ones offered;
  record -> plot round trip;
- the liveliness token reports the publisher lost within 2 s of a SIGKILL;
- killing a subscriber mid-stream leaves the loop's timing unchanged;
- queryables (schema, config, bundle), status/stats/events, and the control queryables only
  when enabled.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("zenoh")

from hil_runtime.telemetry import CycleState, TelemetryConfig, make_sink
from hil_runtime.telemetry.auth import TelemetryAuth, write_client_config, write_users_file
from hil_runtime.telemetry.codec import Schema
from hil_runtime.telemetry.sink import TelemetrySink
from hil_runtime.telemetry.subscriber import TelemetryClient, TelemetryUnavailable, missing_samples
from models.lab.ports import free_loopback_port
from tests.integration.telemetry_fake_loop import JOINTS, FakeLoop, expected_state

REPO = Path(__file__).resolve().parents[2]


def _hil(*args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "hil_runtime.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=REPO,
        check=False,
    )


def _check_record(path: Path, min_samples: int) -> tuple[int, int]:
    with np.load(path) as data:
        record = {name: data[name] for name in data.files}
    schema = Schema.from_json(str(record["schema"]))
    assert schema.joints == JOINTS and list(record["joints"]) == list(JOINTS)
    seq = record["seq"].astype(np.int64)
    assert len(seq) >= min_samples, f"only {len(seq)} samples"
    assert np.all(np.diff(seq) > 0), "samples out of order or duplicated"
    for row in (0, len(seq) // 2, len(seq) - 1):  # decoded values are the ones offered
        expected = expected_state(int(seq[row]))
        for name in ("q", "qd", "q_ref", "qd_ref", "tau", "tau_fb"):
            np.testing.assert_array_equal(record[name][row], expected[name])
        assert record["fallback"][row] == expected["fallback"]
    lost = missing_samples(seq)
    return len(seq), lost


def _record_and_check(tmp_path: Path, seconds: float) -> None:
    port = free_loopback_port()
    loop = FakeLoop(port, seconds=seconds + 30.0)
    out = tmp_path / "run.npz"
    try:
        result = _hil(
            "telemetry",
            "record",
            "--connect",
            loop.endpoint,
            "--seconds",
            str(seconds),
            "--out",
            str(out),
            timeout_s=seconds + 60.0,
        )
        assert result.returncode == 0, result.stderr
        counters = loop.finish()
    finally:
        loop.kill()
    received, lost = _check_record(out, min_samples=int(0.5 * 1000 * seconds))  # the 2-core box may lag 1 kHz
    assert lost <= 0.001 * (received + lost), f"{lost} of {received + lost} samples lost"
    assert counters["dropped"] == 0 and counters["publish_errors"] == 0, counters
    print(f"received {received}, lost {lost} ({100 * lost / (received + lost):.3f} %); {result.stdout.strip()}")

    pytest.importorskip("matplotlib")
    plotted = _hil("telemetry", "plot", str(out))
    assert plotted.returncode == 0, plotted.stderr
    for suffix in ("tracking_error", "torque"):
        png = tmp_path / f"run_{suffix}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_subscriber_process_receives_state_2s_then_plots(tmp_path: Path) -> None:
    _record_and_check(tmp_path, 2.0)


@pytest.mark.heavy
def test_subscriber_process_receives_state_10s(tmp_path: Path) -> None:
    _record_and_check(tmp_path, 10.0)


@pytest.mark.parametrize("how", ["SIGKILL", "SIGSTOP"])
def test_liveliness_reports_a_lost_publisher_within_2s(how: str) -> None:
    """SIGKILL: the kernel closes the socket. SIGSTOP: a hung runtime, socket open: its 1 s lease runs out."""
    port = free_loopback_port()
    loop = FakeLoop(port)
    changes: list[tuple[float, bool]] = []
    seen = threading.Event()
    lost = threading.Event()

    def on_alive(alive: bool) -> None:
        changes.append((time.monotonic(), alive))
        (seen if alive else lost).set()

    try:
        with TelemetryClient.open([loop.endpoint], "fake_arm", timeout_s=5.0) as client:
            client.watch_alive(on_alive)
            assert seen.wait(5.0), "the token was never seen"
            killed_s = time.monotonic()
            os.kill(loop.process.pid, getattr(signal, how))
            assert lost.wait(12.0), "the loss was never reported"
            delay_s = changes[-1][0] - killed_s
            loop.kill()  # a stopped peer would keep Zenoh's close busy 10 s
    finally:
        loop.kill()
    print(f"lost reported {delay_s * 1e3:.0f} ms after {how}")
    assert delay_s <= 2.0


@pytest.mark.parametrize("how", ["SIGKILL", "SIGSTOP"])
def test_a_dead_or_stalled_subscriber_leaves_the_loop_timing_unchanged(tmp_path: Path, how: str) -> None:
    """SIGKILL: the peer's socket closes. SIGSTOP: it stays open and stops reading, so the TCP
    window fills and every put meets a congested link (Zenoh's default 1 ms wait-before-drop,
    spent holding the GIL, raised the loop's p99 lateness from ~150 to ~900 µs here)."""
    port = free_loopback_port()
    timing = tmp_path / "timing.npz"
    loop = FakeLoop(port, seconds=60.0, timing=timing)
    code = (
        "import sys, time\n"
        "from hil_runtime.telemetry.subscriber import TelemetryClient\n"
        f"c = TelemetryClient.open(['{loop.endpoint}'], 'fake_arm')\n"
        "n = [0]\n"
        "def got(p):\n"
        "    n[0] += 1\n"
        "    if n[0] == 200: print('receiving', flush=True)\n"
        "c.subscribe('state', got)\n"
        "time.sleep(60)\n"
    )
    subscriber = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert subscriber.stdout is not None and subscriber.stdout.readline().strip() == "receiving"
        time.sleep(1.0)
        stopped_s = time.monotonic()  # CLOCK_MONOTONIC: the same clock in both processes
        os.kill(subscriber.pid, getattr(signal, how))
        time.sleep(3.0)  # the loop runs on past it
        # A stalled peer keeps Zenoh's session close (not the loop) busy for 10 s at exit: end it first.
        subscriber.kill()
        counters = loop.finish()
    finally:
        subscriber.kill()
        subscriber.wait(10)
        loop.kill()
    with np.load(timing) as data:
        start_s, offer_us, late_us = data["start_s"], data["offer_ns"] / 1e3, data["lateness_s"] * 1e6
    before = (start_s > stopped_s - 1.0) & (start_s <= stopped_s)
    after = (start_s > stopped_s) & (start_s <= stopped_s + 3.0)
    assert before.sum() > 300 and after.sum() > 900
    med_before, med_after = np.median(offer_us[before]), np.median(offer_us[after])
    late_before, late_after = np.percentile(late_us[before], 99), np.percentile(late_us[after], 99)
    print(
        f"{how}: offer_state median {med_before:.1f} -> {med_after:.1f} µs, "
        f"max after {offer_us[after].max():.0f} µs; "
        f"lateness p99 {late_before:.0f} -> {late_after:.0f} µs; cycles/s {before.sum()} -> {after.sum() / 3:.0f}; "
        f"{counters}"
    )
    # The loop never waits on the peer: the hand-off stays a copy, wake-ups stay on time, the rate holds.
    assert med_after <= 2.0 * med_before + 10.0
    assert np.percentile(offer_us[after], 99) <= 2.0 * np.percentile(offer_us[before], 99) + 50.0
    assert offer_us[after].max() < 20_000.0  # one OS preemption on a loaded box, never a wait on the peer
    assert late_after <= 2.0 * late_before + 600.0  # loose: a loaded 2-core machine is noisy
    assert after.sum() / 3 >= 0.9 * before.sum()
    assert counters["publish_errors"] == 0 and counters["dropped"] == 0


class _Controls:
    def __init__(self) -> None:
        self.stops = 0
        self.resets = 0
        self.reset_activates: list[bool | None] = []

    def request_stop(self) -> None:
        self.stops += 1

    def request_reset(self, activate: bool | None = None) -> None:
        self.resets += 1
        self.reset_activates.append(activate)


def credentials(tmp_path: Path) -> tuple[Path, Path]:
    """A usrpwd dictionary (operator, viewer) and the operator's client json5 file."""
    users = write_users_file(tmp_path / "zenoh-users", {"operator": "s3cret", "viewer": "v1ew"})
    return users, write_client_config(tmp_path / "operator.json5", "operator", "s3cret")


def _sink(port: int, controls: _Controls | None, users: Path | None = None) -> TelemetrySink:
    config = TelemetryConfig(
        enabled=True,
        listen=(f"tcp/127.0.0.1:{port}",),
        controls_enabled=controls is not None,
        stats_period_s=0.2,
        auth=None if users is None else TelemetryAuth(users_file=users),
    )
    info = {
        "joints": list(JOINTS),
        "config": {"period_s": 0.001},
        "bundle": {"bundle_id": "pd:0123", "files": {"policy.onnx": "ab" * 32}},
    }
    return make_sink(config, "arm_q", info, controls)


def test_queryables_status_stats_events_and_controls(tmp_path: Path) -> None:
    port = free_loopback_port()
    controls = _Controls()
    users, operator = credentials(tmp_path)
    sink = _sink(port, controls, users)
    sink.start()
    received: dict[str, list[bytes]] = {"status": [], "stats": [], "events": []}
    try:
        with TelemetryClient.open([f"tcp/127.0.0.1:{port}"], None, timeout_s=5.0, config_file=operator) as client:
            assert client.robot == "arm_q"  # found by its liveliness token
            schema = client.schema()
            assert schema.joints == JOINTS
            assert client.query_json("config")["telemetry"]["controls_enabled"] is True
            assert client.query_json("bundle")["files"]["policy.onnx"] == "ab" * 32
            for name, payloads in received.items():
                client.subscribe(name, payloads.append)
            time.sleep(0.5)
            sink.set_status("ACTIVE", None)
            sink.offer_stats({"rate_hz": 1000.0, "overruns": 3})
            sink.event("fault", 12, "EMCY node 2: 0x2310")
            sink.set_status("FAULT", "EMCY node 2")
            time.sleep(0.6)
            assert client.query_json("stop") == {"ok": True, "request": "stop"}
            assert client.query_json("reset") == {"ok": True, "request": "reset"}
    finally:
        sink.close()
    assert controls.stops == 1 and controls.resets == 1
    assert controls.reset_activates == [False]  # a remote reset never enables the drives by itself
    statuses = [schema.decode_status(p)[1] for p in received["status"] if not schema.decode_status(p)[0].warmup]
    assert {"state": "FAULT", "fault": "EMCY node 2", "bundle_id": "pd:0123"} in statuses
    events = [schema.decode_event(p)[1] for p in received["events"]]
    kinds = [(e["kind"], e["detail"]) for e in events if e]
    assert ("fault", "EMCY node 2: 0x2310") in kinds and ("lifecycle", "ACTIVE -> FAULT: EMCY node 2") in kinds
    stats = [schema.decode_stats(p)[1] for p in received["stats"]]
    assert any(s.get("rate_hz") == 1000.0 and s.get("overruns") == 3.0 for s in stats)


def test_no_control_queryables_unless_enabled() -> None:
    port = free_loopback_port()
    sink = _sink(port, None)
    sink.start()
    try:
        with TelemetryClient.open([f"tcp/127.0.0.1:{port}"], "arm_q", timeout_s=5.0) as client:
            client.schema()  # the runtime is reachable...
            with pytest.raises(TelemetryUnavailable, match="no reply from hil/arm_q/stop"):
                client.query("stop", timeout_s=1.0)  # ...but has no stop queryable
        result = _hil("telemetry", "control", "stop", "--connect", f"tcp/127.0.0.1:{port}", "--timeout", "1")
        assert result.returncode == 1
        assert "controls exist only with telemetry.controls_enabled: true" in result.stderr
    finally:
        sink.close()


def test_cli_errors_are_one_line(tmp_path: Path) -> None:
    port = free_loopback_port()
    result = _hil("telemetry", "query", "schema", "--connect", f"tcp/127.0.0.1:{port}", "--timeout", "0.5")
    assert result.returncode == 1 and result.stderr.count("\n") == 1, result.stderr
    assert "no runtime alive at" in result.stderr
    result = _hil("telemetry", "record", "--out", str(tmp_path / "x.txt"), "--connect", f"tcp/127.0.0.1:{port}")
    assert result.returncode == 2 and "unknown record format '.txt' (use .npz, .mcap)" in result.stderr
    result = _hil("telemetry", "plot", str(tmp_path / "missing.npz"))
    assert result.returncode == 2 and "missing.npz: no such file" in result.stderr
    result = _hil("telemetry", "query", "schema", "--connect", "127.0.0.1:7447")
    assert result.returncode == 2 and "--connect: endpoint '127.0.0.1:7447' is not 'proto/host:port'" in result.stderr


def test_watch_shows_the_arm_live() -> None:
    port = free_loopback_port()
    loop = FakeLoop(port)
    try:
        result = subprocess.run(
            [sys.executable, "-m", "hil_runtime.cli", "telemetry", "watch", "--connect", loop.endpoint]
            + "--seconds 1.5 --refresh-hz 4".split(),
            capture_output=True,
            text=True,
            timeout=60,
            cwd=REPO,
            env={**os.environ, "COLUMNS": "140"},
            check=False,
        )
    finally:
        loop.kill()
    assert result.returncode == 0, result.stderr
    last_frame = result.stdout[result.stdout.rfind("hil/fake_arm") :]
    for text in ("alive", "ACTIVE", "q [rad]", "error [rad]", "bundle fake:000000000000", *JOINTS):
        assert text in last_frame, (text, last_frame)


def _acl_example(users: Path, interfaces: str | None = None) -> str:
    """The access-control json5 block of docs/telemetry.md (the one after <!-- acl-example -->),
    with this test's users file."""
    text = (REPO / "docs" / "telemetry.md").read_text()
    block = text.split("<!-- acl-example -->", 1)[1].split("```json5\n", 1)[1].split("```", 1)[0]
    assert 'dictionary_file: "/etc/hil/zenoh-users"' in block
    block = block.replace("/etc/hil/zenoh-users", str(users))
    if interfaces is not None:
        assert 'interfaces: ["eth0", "wlan0"]' in block
        block = block.replace('interfaces: ["eth0", "wlan0"]', f"interfaces: {interfaces}")
    return block


# Queries whose key expressions intersect hil/arm_q/stop or /reset without being them.
WILDCARDS = ("hil/arm_q/**", "hil/*/stop", "hil/*/reset", "hil/arm_q/re$*", "hil/arm_q/st$*", "hil/**", "hil/arm_q/*")


def _reply(reply: Any) -> tuple[str, bytes]:
    if reply.ok is not None:
        return "ok", reply.ok.payload.to_bytes()
    return "err", reply.err.payload.to_bytes()


def raw_gets(
    endpoint: str, keys: tuple[str, ...], user: str | None = None, password: str | None = None
) -> dict[str, list[tuple[str, bytes]]]:
    """Every reply to each of ``keys`` (sent at once) from a plain Zenoh session (no hil code),
    as (ok|err, payload)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    if user is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    session = zenoh.open(conf)
    try:
        time.sleep(0.3)  # the link is up (or refused)
        pending = {key: session.get(key, timeout=1.0, target=zenoh.QueryTarget.ALL) for key in keys}
        return {key: [_reply(r) for r in replies] for key, replies in pending.items()}
    finally:
        session.close()


@pytest.mark.parametrize(("interfaces", "stop_allowed"), [('["lo"]', False), (None, True)])
def test_the_documented_access_control_restricts_the_controls(
    tmp_path: Path, interfaces: str | None, stop_allowed: bool
) -> None:
    """The docs' file verbatim (users file and interfaces substituted): an unauthenticated session
    gets nothing; wildcard queries never reach stop/reset; with the rule applied to loopback, the
    exact stop is refused and schema still answers; as documented (network interfaces only), an
    authenticated stop from this machine goes through."""
    users, operator = credentials(tmp_path)
    acl = tmp_path / "acl.json5"
    acl.write_text(_acl_example(users, interfaces))
    port = free_loopback_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    controls = _Controls()
    config = TelemetryConfig(enabled=True, listen=(endpoint,), controls_enabled=True, zenoh_config=acl)
    sink = make_sink(config, "arm_q", {"joints": list(JOINTS)}, controls)
    sink.start()
    try:
        every = ("hil/arm_q/stop", "hil/arm_q/reset", "hil/arm_q/schema", *WILDCARDS)
        for user, password in ((None, None), ("operator", "wrong")):
            answered = {key: r for key, r in raw_gets(endpoint, every, user, password).items() if r}
            assert answered == {}, f"{user or 'no user'}: replies without authentication"
        answers = raw_gets(endpoint, WILDCARDS, "operator", "s3cret")
        for key, replies in answers.items():
            assert not [p for kind, p in replies if kind == "ok" and b'"request"' in p], (key, replies)
        assert any(kind == "ok" for kind, _ in answers["hil/arm_q/**"]), "the operator's session is not connected"
        assert controls.stops == 0 and controls.resets == 0, "a wildcard query reached a control"
        with TelemetryClient.open([endpoint], "arm_q", timeout_s=5.0, config_file=operator) as client:
            assert client.schema().joints == JOINTS
            if stop_allowed:
                assert client.query_json("stop") == {"ok": True, "request": "stop"}
            else:
                with pytest.raises(TelemetryUnavailable, match="no reply from hil/arm_q/stop"):
                    client.query("stop", timeout_s=1.5)
                with pytest.raises(TelemetryUnavailable, match="no reply from hil/arm_q/reset"):
                    client.query("reset", timeout_s=1.5)
    finally:
        sink.close()
    assert controls.stops == (1 if stop_allowed else 0) and controls.resets == 0


def test_close_is_bounded_with_a_stalled_subscriber() -> None:
    port = free_loopback_port()
    sink = make_sink(
        TelemetryConfig(enabled=True, listen=(f"tcp/127.0.0.1:{port}",), close_timeout_s=0.5),
        "arm_q",
        {"joints": list(JOINTS)},
    )
    sink.start()
    code = (
        "import time\n"
        "from hil_runtime.telemetry.subscriber import TelemetryClient\n"
        f"c = TelemetryClient.open(['tcp/127.0.0.1:{port}'], 'arm_q')\n"
        "n = [0]\n"
        "def got(p):\n"
        "    n[0] += 1\n"
        "    if n[0] == 100: print('receiving', flush=True)\n"
        "c.subscribe('state', got)\n"
        "time.sleep(60)\n"
    )
    subscriber = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    stop = threading.Event()
    zeros = np.zeros(len(JOINTS))

    def feed() -> None:
        seq = 0
        while not stop.is_set():
            sink.offer_state(CycleState(seq, 0, zeros, zeros, zeros, zeros, zeros, zeros, 0.0, 0.0))
            seq += 1
            time.sleep(0.001)

    feeder = threading.Thread(target=feed)
    feeder.start()
    try:
        assert subscriber.stdout is not None and subscriber.stdout.readline().strip() == "receiving"
        os.kill(subscriber.pid, signal.SIGSTOP)
        time.sleep(1.5)  # its TCP window fills: the link cannot be flushed
        stop.set()
        feeder.join()
        begin = time.monotonic()
        sink.close()
        took_s = time.monotonic() - begin
    finally:
        stop.set()
        subscriber.kill()
        subscriber.wait(10)
    for thread in threading.enumerate():  # Zenoh finishes once the peer is gone
        if thread.name == "telemetry-close":
            thread.join(15)
    print(f"close took {took_s:.2f} s with a stalled subscriber")
    assert took_s < 0.5 + 0.5


def test_a_port_in_use_is_one_line() -> None:
    from hil_runtime.telemetry.publisher import TelemetryStartError

    port = free_loopback_port()
    config = TelemetryConfig(enabled=True, listen=(f"tcp/127.0.0.1:{port}",))
    first = make_sink(config, "arm_q", {"joints": list(JOINTS)})
    first.start()
    try:
        with pytest.raises(TelemetryStartError) as info:
            make_sink(config, "arm_q", {"joints": list(JOINTS)}).start()
    finally:
        first.close()
    text = str(info.value)
    assert text.startswith(f"telemetry: cannot open the Zenoh session (listen tcp/127.0.0.1:{port}): ")
    assert "Address already in use" in text and ".rs:" not in text and "\n" not in text
    assert info.value.exit_code == 2
