"""The runtime with the real Zenoh sink (on 127.0.0.1, scouting off): state samples every cycle,
status on lifecycle changes, stats fields all in the schema, and the Zenoh stop queryable stops
the loop through ``request_stop`` (the telemetry issue's controls), for an authenticated peer only;
a Zenoh reset clears a FAULT to INACTIVE and never enables the drives by itself (issue 20)."""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from drivers.testing import FakeJointBus
from hil_runtime.config import parse_runtime_config
from hil_runtime.factory import build_runtime
from hil_runtime.lifecycle import LifecycleState
from hil_runtime.telemetry.auth import write_users_file
from models.lab.ports import free_loopback_port
from sim_target.testing.ur5 import MAX_TORQUE_NM, Q0_RAD
from tests.unit.hil_runtime.support import NO_OVERRUN_BUDGET, config_dict

zenoh = pytest.importorskip("zenoh")


def _session(endpoint: str, user: str | None = None, password: str | None = None) -> Any:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("listen/endpoints", "[]")
    if user is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return zenoh.open(conf)


def _controlled(tmp_path: Path, endpoint: str, **telemetry: Any) -> Any:
    users = write_users_file(tmp_path / "users", {"operator": "s3cret"})
    section = {"enabled": True, "listen": [endpoint], "controls_enabled": True, "auth": {"users_file": str(users)}}
    return parse_runtime_config(
        config_dict(loop={"pacing": "clock"}, safety=NO_OVERRUN_BUDGET, telemetry={**section, **telemetry}), "rt.yaml"
    )


def test_state_status_and_the_stop_queryable(caplog: pytest.LogCaptureFixture, tmp_path: Path) -> None:
    port = free_loopback_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    config = _controlled(tmp_path, endpoint)
    bus = FakeJointBus(6, period_s=0.001, inertia_kgm2=1.0, max_torque_nm=MAX_TORQUE_NM, initial_position_rad=Q0_RAD)
    runtime = build_runtime(config, bus)

    samples = {"state": 0, "status": 0}
    caplog.set_level(logging.WARNING, logger="hil_runtime.telemetry")
    runtime.configure()  # the sink starts: the session listens
    session = _session(endpoint, "operator", "s3cret")
    stranger = _session(endpoint)  # no credentials: refused at the handshake
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
        assert [r for r in stranger.get("hil/ur5_paper/stop", timeout=1.0)] == []
        assert runtime.state is LifecycleState.ACTIVE and thread.is_alive()
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
        stranger.close()
        runtime.shutdown()
    assert not [r for r in caplog.records if "not in the schema" in r.getMessage()]


@pytest.mark.parametrize("remote_reset_activates", [False, True])
def test_a_zenoh_reset_clears_the_fault_to_inactive(tmp_path: Path, remote_reset_activates: bool) -> None:
    """loop.activate_on_reset is on (a local reset re-enables the drives), yet a reset over Zenoh
    stops at INACTIVE with the drives off, unless telemetry.remote_reset_activates says otherwise."""
    from drivers.errors import DriveFaultError

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    config = _controlled(tmp_path, endpoint, remote_reset_activates=remote_reset_activates)
    assert config.loop.activate_on_reset
    bus = FakeJointBus(6, period_s=0.001, inertia_kgm2=1.0, max_torque_nm=MAX_TORQUE_NM, initial_position_rad=Q0_RAD)
    runtime = build_runtime(config, bus)
    runtime.configure()
    session = _session(endpoint, "operator", "s3cret")
    thread = threading.Thread(target=runtime.run)
    try:
        runtime.activate()
        runtime.run(max_cycles=20)
        bus.fail_next_exchange(DriveFaultError(4, 0x2310, "EMCY"))
        assert runtime.run(max_cycles=20, stop_on_fault=True).reason == "fault"
        thread.start()  # the loop waits in FAULT for a reset, as the daemon's does
        assert not bus.enabled
        replies = [r.ok.payload.to_bytes() for r in session.get("hil/ur5_paper/reset", timeout=5.0) if r.ok]
        assert replies and json.loads(replies[0]) == {"ok": True, "request": "reset"}
        wanted = LifecycleState.ACTIVE if remote_reset_activates else LifecycleState.INACTIVE
        deadline = time.monotonic() + 5.0
        while runtime.state is not wanted and time.monotonic() < deadline:
            time.sleep(0.005)
        time.sleep(0.1)  # and it stays there
        assert runtime.state is wanted
        assert "fault_reset" in bus.events and bus.enabled is remote_reset_activates
    finally:
        runtime.request_stop()
        thread.join(5)
        session.close()
        runtime.shutdown()
