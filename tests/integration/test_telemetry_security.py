"""issue 20, Zenoh: who may join the runtime's session, and who publishes as hil/<robot>.

- with ``auth``, a session without credentials (or with a wrong password) gets no link to the
  runtime at all: no peer, no reply, no sample;
- ``hil telemetry record`` and ``watch`` name the publishing session (Zenoh id) and warn when a
  second session (here an impersonator the subscriber also reaches, with an alive token, a schema
  queryable and fake state) publishes as the same robot.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from models.lab.ports import free_loopback_port

zenoh = pytest.importorskip("zenoh")

from hil_runtime.telemetry import CycleState, TelemetryConfig, make_sink  # noqa: E402
from hil_runtime.telemetry.auth import TelemetryAuth, write_users_file  # noqa: E402
from hil_runtime.telemetry.codec import build_schema, encode_state  # noqa: E402
from tests.integration.test_telemetry_zenoh import JOINTS, REPO  # noqa: E402


def _session(listen: list[str], connect: list[str], user: str | None = None, password: str | None = None) -> Any:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    if user is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return zenoh.open(conf)


@contextmanager
def _runtime(endpoint: str, users: Path | None = None) -> Iterator[Any]:
    """The real sink, fed ~500 state samples a second from a thread."""
    config = TelemetryConfig(
        enabled=True, listen=(endpoint,), auth=None if users is None else TelemetryAuth(users_file=users)
    )
    sink = make_sink(config, "arm_q", {"joints": list(JOINTS)})
    sink.start()
    stop = threading.Event()
    zeros = np.zeros(len(JOINTS))

    def feed() -> None:
        seq = 0
        while not stop.is_set():
            sink.offer_state(CycleState(seq, time.monotonic_ns(), zeros, zeros, zeros, zeros, zeros, zeros, 0.0, 0.0))
            seq += 1
            time.sleep(0.002)

    feeder = threading.Thread(target=feed)
    feeder.start()
    try:
        yield sink
    finally:
        stop.set()
        feeder.join()
        sink.close()


@contextmanager
def _impersonator(endpoint: str) -> Iterator[Any]:
    """Another uid's session: the robot's alive token, a schema queryable, fake state."""
    session = _session([endpoint], [])
    schema = json.dumps(build_schema("arm_q", list(JOINTS))).encode()
    queryable = session.declare_queryable("hil/arm_q/schema", lambda query: query.reply("hil/arm_q/schema", schema))
    token = session.liveliness().declare_token("hil/arm_q/alive")
    publisher = session.declare_publisher("hil/arm_q/state")
    stop = threading.Event()
    fake = [np.full(len(JOINTS), 1.0)] * 6

    def feed() -> None:
        seq = 10_000_000
        while not stop.is_set():
            publisher.put(encode_state(seq, time.monotonic_ns(), fake, 0.0, 0.0))
            seq += 1
            time.sleep(0.005)

    feeder = threading.Thread(target=feed)
    feeder.start()
    try:
        yield session
    finally:
        stop.set()
        feeder.join()
        for entity in (publisher, token, queryable):
            entity.undeclare()
        session.close()


def _record(tmp_path: Path, *connect: str) -> tuple[subprocess.CompletedProcess[str], dict[str, Any]]:
    out = tmp_path / "run.npz"
    argv = [sys.executable, "-m", "hil_runtime.cli", "telemetry", "record", "--robot", "arm_q", "--seconds", "1.5"]
    for endpoint in connect:
        argv += ["--connect", endpoint]
    done = subprocess.run(
        [*argv, "--out", str(out), "--timeout", "10"], capture_output=True, text=True, timeout=60, cwd=REPO, check=False
    )
    assert done.returncode == 0, done.stderr
    with np.load(out) as data:
        return done, json.loads(str(data["publishers"]))


def test_record_names_the_publisher_and_warns_when_two_sessions_publish(tmp_path: Path) -> None:
    runtime_endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    fake_endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    with _runtime(runtime_endpoint) as sink:
        zid = str(sink._session.zid())
        done, publishers = _record(tmp_path, runtime_endpoint)
        assert "warning" not in done.stderr and f"published by {zid}" in done.stdout, (done.stdout, done.stderr)
        assert list(publishers["samples"]) == [zid] and publishers["schema_repliers"] == [zid]
        with _impersonator(fake_endpoint) as fake:
            done, publishers = _record(tmp_path, runtime_endpoint, fake_endpoint)
            fake_zid = str(fake.zid())
    assert "warning: several Zenoh sessions publish as hil/arm_q" in done.stderr, done.stderr
    assert zid in done.stderr and fake_zid in done.stderr
    assert zid in publishers["samples"] and len(publishers["samples"]) == 2  # the fake: no source info
    assert sorted(publishers["schema_repliers"]) == sorted([zid, fake_zid])


def test_watch_warns_when_two_sessions_publish() -> None:
    runtime_endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    fake_endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    with _runtime(runtime_endpoint), _impersonator(fake_endpoint):
        done = subprocess.run(
            [sys.executable, "-m", "hil_runtime.cli", "telemetry", "watch", "--robot", "arm_q"]
            + ["--connect", runtime_endpoint, "--connect", fake_endpoint, "--seconds", "1.5", "--refresh-hz", "4"],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=REPO,
            env={**os.environ, "COLUMNS": "200"},
            check=False,
        )
    assert done.returncode == 0, done.stderr
    assert "WARNING: several Zenoh sessions publish as hil/arm_q" in done.stdout, done.stdout[-2000:]


def test_with_auth_an_unauthenticated_session_cannot_join(tmp_path: Path) -> None:
    users = write_users_file(tmp_path / "users", {"viewer": "v1ew"})
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    with _runtime(endpoint, users) as sink:
        runtime_zid = str(sink._session.zid())
        for user, password in ((None, None), ("viewer", "wrong"), ("intruder", "v1ew")):
            stranger = _session([], [endpoint], user, password)
            try:
                received: list[bytes] = []
                stranger.declare_subscriber("hil/arm_q/**", lambda sample: received.append(sample.payload.to_bytes()))
                stranger.liveliness().declare_token("hil/arm_q/alive")
                time.sleep(0.5)
                assert list(stranger.info.peers_zid()) == [], f"{user}: a link to the runtime"
                assert [r for r in stranger.get("hil/arm_q/schema", timeout=0.5)] == []
                assert received == []
            finally:
                stranger.close()
        viewer = _session([], [endpoint], "viewer", "v1ew")
        try:
            time.sleep(0.5)
            assert [str(z) for z in viewer.info.peers_zid()] == [runtime_zid]
            assert [r.ok is not None for r in viewer.get("hil/arm_q/schema", timeout=2.0)] == [True]
        finally:
            viewer.close()
