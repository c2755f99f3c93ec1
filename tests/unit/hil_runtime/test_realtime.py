"""Real-time hygiene: where the OS refuses, one warning and carry on; gc off inside the loop."""

from __future__ import annotations

import ctypes
import errno
import gc
import logging
import os
import threading

import pytest

from hil_runtime import realtime
from hil_runtime.realtime import (
    GcQuiet,
    RealtimeReport,
    set_thread_affinity,
    set_thread_fifo,
)


def _eperm(*args: object) -> None:
    raise PermissionError(errno.EPERM, "Operation not permitted")


def test_refusals_are_one_warning_each_and_not_errors(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(os, "sched_setscheduler", _eperm)
    monkeypatch.setattr(os, "sched_setaffinity", _eperm)
    report = RealtimeReport()
    with caplog.at_level(logging.WARNING, logger="hil_runtime.realtime"):
        assert set_thread_fifo(80, report) is False
        assert set_thread_affinity((1,), report) is False
    assert report.applied == [] and len(report.refused) == 2
    assert "Operation not permitted" in report.refused[0]
    assert len(caplog.records) == 2 and all("carrying on" in r.getMessage() for r in caplog.records)


def test_mlockall_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    class Libc:
        def mlockall(self, flags: int) -> int:
            assert flags == realtime.MCL_CURRENT | realtime.MCL_FUTURE
            return -1

    monkeypatch.setattr(ctypes, "CDLL", lambda *a, **k: Libc())  # the module realtime calls through
    monkeypatch.setattr(ctypes, "get_errno", lambda: errno.EPERM)
    report = RealtimeReport()
    assert realtime.lock_memory(report) is False
    assert report.refused and "EPERM" in report.refused[0]


def test_affinity_acts_on_the_calling_thread_only() -> None:
    if not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2:
        pytest.skip("needs two CPUs")
    before = os.sched_getaffinity(0)
    cpu = min(before)
    seen: dict[str, object] = {}

    def worker() -> None:
        seen["ok"] = set_thread_affinity((cpu,))
        seen["inside"] = os.sched_getaffinity(0)

    thread = threading.Thread(target=worker)
    thread.start()
    thread.join()
    assert seen["ok"] and seen["inside"] == {cpu}
    assert os.sched_getaffinity(0) == before  # this thread untouched


def test_gc_is_off_inside_and_restored() -> None:
    assert gc.isenabled()
    with GcQuiet():
        assert not gc.isenabled()
    assert gc.isenabled()


def test_clock_pacing_on_a_loaded_machine_without_fifo_is_said_once(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    monkeypatch.setattr(os, "getloadavg", lambda: (1.5, 1.0, 1.0))
    assert realtime.clock_pacing_risk(0.001, fifo_applied=False) is None  # below the CPU count
    monkeypatch.setattr(os, "getloadavg", lambda: (2.5, 1.0, 1.0))
    risk = realtime.clock_pacing_risk(0.001, fifo_applied=False)
    assert risk is not None and "1000 Hz without SCHED_FIFO" in risk and "load average 2.5 on 2 CPUs" in risk
    assert realtime.clock_pacing_risk(0.001, fifo_applied=True) is None  # SCHED_FIFO holds the period


def test_the_runtime_warns_of_clock_pacing_risk_before_active(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    from drivers.testing import FakeJointBus
    from hil_runtime.config import parse_runtime_config
    from hil_runtime.runtime import Runtime
    from tests.unit.hil_runtime.support import config_dict
    from tests.unit.hil_runtime.test_runtime_loop import RecordingSink

    monkeypatch.setattr(os, "getloadavg", lambda: (64.0, 64.0, 64.0))
    for pacing, warned in (("clock", True), ("bus", False)):
        sink = RecordingSink()
        config = parse_runtime_config(config_dict(loop={"pacing": pacing, "warmup_cycles": 5}), "rt.yaml")
        runtime = Runtime(config, FakeJointBus(6, period_s=0.001), telemetry=sink)
        runtime.configure()
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="hil_runtime.runtime"):
            runtime.activate()
            runtime.run(max_cycles=3, stop_on_fault=True)
        runtime.shutdown()
        said = [detail for kind, _, detail in sink.events if kind == "warning" and "clock pacing" in detail]
        logged = [r for r in caplog.records if "clock pacing" in r.getMessage()]
        assert (len(said), len(logged)) == ((1, 1) if warned else (0, 0)), (pacing, sink.events)
