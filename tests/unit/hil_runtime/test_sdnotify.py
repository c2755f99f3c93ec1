"""systemd's notify protocol through a Unix datagram socket of our own as NOTIFY_SOCKET: READY,
STATUS, WATCHDOG at half of WATCHDOG_USEC from the loop, none while the loop is stalled, STOPPING."""

from __future__ import annotations

import os
import socket
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from drivers.testing import FakeJointBus
from hil_runtime.config import parse_runtime_config
from hil_runtime.runtime import Runtime
from hil_runtime.sdnotify import Notifier
from sim_target.testing.notify import NotifyListener
from sim_target.testing.ur5 import MAX_TORQUE_NM, Q0_RAD
from tests.unit.hil_runtime.support import StubBundle, config_dict


@pytest.fixture
def listener(tmp_path: Path):
    path = str(tmp_path / "notify.sock")
    lst = NotifyListener(path)
    yield path, lst
    lst.close()


def test_environment_rules(listener: tuple) -> None:
    path, _ = listener
    assert not Notifier.from_environment({}).enabled
    n = Notifier.from_environment({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"})
    assert n.enabled and n.watchdog_interval_s == pytest.approx(1.0)
    other = Notifier.from_environment({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"})
    assert other.watchdog_interval_s is None  # the watchdog is someone else's
    mine = Notifier.from_environment(
        {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "100000", "WATCHDOG_PID": str(os.getpid())}
    )
    assert mine.watchdog_interval_s == pytest.approx(0.05)
    for notifier in (n, other, mine):
        notifier.close()


def test_abstract_namespace_socket() -> None:
    name = f"hil-test-{uuid.uuid4().hex[:8]}"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind("\0" + name)
    server.settimeout(2)
    try:
        notifier = Notifier(f"@{name}")
        assert notifier.status("hello")
        assert server.recv(100) == b"STATUS=hello"
        notifier.close()
    finally:
        server.close()


def test_a_missing_socket_never_raises() -> None:
    notifier = Notifier("/nonexistent/notify.sock", 1000)
    assert notifier.ready("x") is False and notifier.failed == 1
    notifier.watchdog_if_due(0.0)
    notifier.close()


def _runtime(notifier: Notifier, bundle: StubBundle) -> Runtime:
    # The stall below is longer than the overrun budget allows a real arm: this test is about the
    # watchdog, so the budget is set past it (the budget's own tests: test_overruns.py).
    config = parse_runtime_config(
        config_dict(loop={"pacing": "clock", "idle_poll_s": 0.005}, safety={"overrun_budget": 100_000}), "rt.yaml"
    )
    bus = FakeJointBus(6, period_s=0.001, inertia_kgm2=1.0, max_torque_nm=MAX_TORQUE_NM, initial_position_rad=Q0_RAD)
    return Runtime(config, bus, bundle=bundle, notifier=notifier)


def test_ready_status_watchdog_from_the_loop_and_a_stall_stops_the_pings(listener: tuple) -> None:
    path, lst = listener
    notifier = Notifier.from_environment({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "40000"})  # pings every 20 ms
    bundle = StubBundle()
    stall = threading.Event()
    release = threading.Event()

    def stall_if_asked() -> None:
        if stall.is_set():
            release.wait(5)  # the loop hangs inside the policy call
            stall.clear()

    bundle.before_step = stall_if_asked
    rt = _runtime(notifier, bundle)
    rt.configure()
    thread = threading.Thread(target=rt.run, kwargs={"shutdown_at_end": True})
    rt.request_activate()
    thread.start()
    time.sleep(0.3)
    stall.set()
    time.sleep(0.3)  # stalled: 15 watchdog intervals without a ping
    stalled_from = time.monotonic() - 0.3
    release.set()
    time.sleep(0.2)
    rt.request_stop()
    thread.join(5)
    notifier.close()
    time.sleep(0.1)

    ready = lst.with_key("READY")
    assert len(ready) == 1 and ready[0][1]["READY"] == "1" and ready[0][1]["STATUS"].startswith("ACTIVE")
    assert ready[0][1]["MAINPID"] == str(os.getpid())
    pings = [t for t, f in lst.with_key("WATCHDOG") if f["WATCHDOG"] == "1"]
    before = [t for t in pings if t < stalled_from]
    assert len(before) >= 4  # ~every 20 ms while healthy (fewer when the machine is loaded)
    gaps = np.diff(pings)
    assert gaps.max() > 0.25  # the stall: no pings for its whole length...
    assert sum(1 for t in pings if stalled_from + 0.02 < t < stalled_from + 0.28) == 0
    assert pings[-1] > stalled_from + 0.3  # ...and they resume once the loop moves again
    assert np.median(gaps) == pytest.approx(0.02, abs=0.015)
    statuses = [f["STATUS"] for _, f in lst.with_key("STATUS")]
    assert any(s.startswith("ACTIVE") and "Hz" in s for s in statuses)
    stopping = lst.with_key("STOPPING")
    assert stopping and stopping[-1][1]["STOPPING"] == "1"
    assert stopping[-1][0] >= ready[0][0]


def test_fault_reason_goes_to_status_and_the_idle_thread_keeps_pinging(listener: tuple) -> None:
    path, lst = listener
    notifier = Notifier.from_environment({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "40000"})
    bundle = StubBundle()
    rt = _runtime(notifier, bundle)
    rt.configure()
    rt.activate()
    bundle.tau_value = np.full(6, np.nan)
    bundle.tau_fb_value = np.full(6, np.nan)
    thread = threading.Thread(target=rt.run)
    thread.start()
    time.sleep(0.3)
    rt.request_stop()
    thread.join(5)
    rt.shutdown()
    notifier.close()
    time.sleep(0.1)
    statuses = [f["STATUS"] for _, f in lst.with_key("STATUS")]
    assert any(s.startswith("FAULT: policy_nonfinite") for s in statuses), statuses
    fault_t = next(t for t, f in lst.with_key("STATUS") if f["STATUS"].startswith("FAULT"))
    assert sum(1 for t, _ in lst.with_key("WATCHDOG") if t > fault_t) >= 3  # alive, waiting for a reset
