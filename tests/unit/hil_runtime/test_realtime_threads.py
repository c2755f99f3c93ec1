"""The loop thread's real-time settings as the runtime applies them: SCHED_FIFO and a CPU for the
loop thread only, the helper threads (created before, SCHED_OTHER) moved off that CPU, and the
free-running demo asking for them (it never did: the "refused" SCHED_FIFO was never requested)."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import pytest

from drivers.testing import FakeJointBus
from hil_runtime.config import parse_runtime_config
from hil_runtime.realtime import keep_other_threads_off
from hil_runtime.runtime import Runtime
from sim_target.testing.ur5 import MAX_TORQUE_NM, Q0_RAD
from tests.unit.hil_runtime.support import StubBundle, config_dict

needs_two_cpus = pytest.mark.skipif(
    not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs"
)


@pytest.fixture
def restored_affinity() -> Iterator[None]:
    """Every thread of this process back on its CPUs after the test (the helpers were moved)."""
    saved = {int(t): os.sched_getaffinity(int(t)) for t in os.listdir("/proc/self/task")}
    yield
    for tid, cpus in saved.items():
        try:
            os.sched_setaffinity(tid, cpus)
        except ProcessLookupError:
            pass


def _helper() -> tuple[threading.Thread, threading.Event, dict[str, int]]:
    ready, done, ids = threading.Event(), threading.Event(), {}

    def run() -> None:
        ids["tid"] = threading.get_native_id()
        ready.set()
        done.wait(10)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    ready.wait(5)
    return thread, done, ids


@needs_two_cpus
def test_helper_threads_leave_the_loop_cpu_and_the_caller_keeps_its_own(restored_affinity: None) -> None:
    cpu = max(os.sched_getaffinity(0))
    thread, done, ids = _helper()
    seen: dict[str, bool] = {}
    mine: set[int] = set()  # the loop thread's CPUs, as it saw them

    def loop() -> None:
        seen["ok"] = keep_other_threads_off((cpu,))
        mine.update(os.sched_getaffinity(0))

    caller = threading.Thread(target=loop)
    caller.start()
    caller.join(5)
    done.set()
    assert seen["ok"] is True
    assert cpu not in os.sched_getaffinity(ids["tid"]) and cpu not in os.sched_getaffinity(0)
    assert cpu in mine


@needs_two_cpus
def test_the_loop_thread_gets_fifo_and_its_cpu_helpers_keep_sched_other(restored_affinity: None) -> None:
    if os.geteuid() != 0:
        pytest.skip("SCHED_FIFO needs root or RLIMIT_RTPRIO")
    cpu = max(os.sched_getaffinity(0))
    thread, done, ids = _helper()  # a helper made before the loop thread, as the publisher is
    config = parse_runtime_config(config_dict(loop={"pacing": "bus", "cpu_affinity": [cpu], "fifo_priority": 10}))
    bus = FakeJointBus(6, period_s=0.001, max_torque_nm=MAX_TORQUE_NM, initial_position_rad=Q0_RAD)
    rt = Runtime(config, bus, bundle=StubBundle())
    rt.configure()
    rt.activate()
    seen: dict[str, object] = {}

    def loop() -> None:
        rt.run(max_cycles=20)
        seen["policy"] = os.sched_getscheduler(0)
        seen["cpus"] = os.sched_getaffinity(0)

    caller = threading.Thread(target=loop)
    caller.start()
    caller.join(10)
    rt.shutdown()
    assert seen["policy"] == os.SCHED_FIFO and seen["cpus"] == {cpu}
    assert os.sched_getscheduler(ids["tid"]) == os.SCHED_OTHER
    assert cpu not in os.sched_getaffinity(ids["tid"])
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # this (test) thread untouched
    assert any(a.startswith("SCHED_FIFO") for a in rt.realtime.applied) and not rt.realtime.refused
    done.set()


def test_the_free_running_demo_asks_for_fifo_a_cpu_and_locked_memory(tmp_path: Path) -> None:
    from models.demo.configs import runtime_config
    from models.demo.options import DemoOptions
    from models.robots import load_robot

    robot = load_robot("ur5_paper")
    condition = SimpleNamespace(name="C1", duration_s=5.0)
    args = (robot, condition, 0.001, tmp_path, tmp_path / "c.yaml", tmp_path / "s.sock", "tcp/127.0.0.1:7447")
    free = runtime_config(DemoOptions(realtime=True), *args)["loop"]
    assert free["fifo_priority"] >= 1 and free["lock_memory"] is True
    if len(os.sched_getaffinity(0)) > 1:
        assert free["cpu_affinity"] and len(free["cpu_affinity"]) < len(os.sched_getaffinity(0))
    lockstep = runtime_config(DemoOptions(realtime=False), *args)["loop"]
    # lock-step hands off between two threads every cycle: FIFO keeps the hand-off prompt (docs/runtime.md),
    # but it pins no CPU and locks no memory, a lock-step run is a lab run
    assert lockstep["fifo_priority"] >= 1
    assert "cpu_affinity" not in lockstep and not lockstep.get("lock_memory", False)
