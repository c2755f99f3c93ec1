"""The runtime with the real Zenoh sink (on 127.0.0.1, scouting off): state samples every cycle,
status on lifecycle changes, stats fields all in the schema, and the Zenoh stop queryable stops
the loop through ``request_stop`` (the telemetry issue's controls)."""

from __future__ import annotations

import json
import logging
import socket
import threading
import time

import pytest

from drivers.testing import FakeJointBus
from hil_runtime.config import parse_runtime_config
from hil_runtime.daemon import make_telemetry
from hil_runtime.runtime import Runtime
from sim_target.testing.ur5 import MAX_TORQUE_NM, Q0_RAD
from tests.unit.hil_runtime.support import config_dict

zenoh = pytest.importorskip("zenoh")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_state_status_and_the_stop_queryable(caplog: pytest.LogCaptureFixture) -> None:
    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    config = parse_runtime_config(
        config_dict(
            loop={"pacing": "clock"}, telemetry={"enabled": True, "listen": [endpoint], "controls_enabled": True}
        ),
        "rt.yaml",
    )
    bus = FakeJointBus(6, period_s=0.001, inertia_kgm2=1.0, max_torque_nm=MAX_TORQUE_NM, initial_position_rad=Q0_RAD)
    runtime = Runtime(config, bus)
    runtime.telemetry = make_telemetry(config, runtime)

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("listen/endpoints", "[]")
    samples = {"state": 0, "status": 0}
    caplog.set_level(logging.WARNING, logger="hil_runtime.telemetry")
    runtime.configure()  # the sink starts: the session listens
    session = zenoh.open(conf)
    try:
        subs = [
            session.declare_subscriber(
                f"hil/ur5_paper/{key}", lambda sample, key=key: samples.__setitem__(key, samples[key] + 1)
            )
            for key in ("state", "status")
        ]
        time.sleep(0.5)  # the peers connect
        runtime.request_activate()
        thread = threading.Thread(target=runtime.run, kwargs={"shutdown_at_end": True})
        thread.start()
        time.sleep(1.0)
        replies = [r.ok.payload.to_bytes() for r in session.get("hil/ur5_paper/stop", timeout=5.0) if r.ok]
        thread.join(5)
        assert not thread.is_alive(), "the stop queryable did not stop the loop"
        assert replies and json.loads(replies[0])["ok"] is True
        assert runtime.state.value == "FINALIZED"
        assert samples["state"] > 100, samples  # ~1 kHz for ~1 s (fewer on a loaded machine)
        assert samples["status"] >= 1
        for sub in subs:
            sub.undeclare()
    finally:
        session.close()
        runtime.shutdown()
    assert not [r for r in caplog.records if "not in the schema" in r.getMessage()]
