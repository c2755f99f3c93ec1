"""What the fault campaign (issue 15, docs/faults.md) needs the runtime to report, on a fake bus:
the first stale cycle as an event at once, counter rises as one ``warning`` event per stats
interval, a policy with nothing finite as FAULT policy_nonfinite, counters in the status, and
the record written whole or not at all."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.testing import FakeJointBus
from hil_runtime.bundle import PolicyBundle
from hil_runtime.config import parse_runtime_config
from hil_runtime.lifecycle import LifecycleState
from hil_runtime.runtime import RunRecord, Runtime
from hil_runtime.telemetry.sink import CycleState, NullTelemetry
from sim_target.testing.ur5 import MAX_TORQUE_NM, PD_BUNDLE, Q0_RAD
from tests.unit.hil_runtime.support import StubBundle, config_dict


class Events(NullTelemetry):
    def __init__(self) -> None:
        self.events: list[tuple[str, int, str]] = []

    def event(self, kind: str, cycle: int, detail: str) -> None:
        self.events.append((kind, cycle, detail))


def _runtime(
    bundle: PolicyBundle | None = None, record: int = 0, **overrides: Any
) -> tuple[Runtime, FakeJointBus, Events]:
    bus = FakeJointBus(
        6,
        period_s=0.001,
        inertia_kgm2=(2.0, 2.0, 1.0, 0.2, 0.2, 0.1),
        max_torque_nm=MAX_TORQUE_NM,
        initial_position_rad=Q0_RAD,
    )
    sink = Events()
    config = parse_runtime_config(config_dict(**overrides), "rt.yaml")
    runtime = Runtime(config, bus, bundle=bundle, telemetry=sink, record_cycles=record)
    runtime.configure()
    assert runtime.activate()
    return runtime, bus, sink


def test_the_first_stale_cycle_is_an_event_at_once_and_the_rise_a_warning() -> None:
    runtime, bus, sink = _runtime(loop={"stats_interval_s": 1e-6})  # stats every cycle
    runtime.run(max_cycles=10)
    sink.events.clear()
    injected = runtime.total_cycles
    bus.make_stale([2], cycles=1)  # tolerated: max_stale_cycles 1
    runtime.run(max_cycles=5)
    assert runtime.state is LifecycleState.ACTIVE
    stale = [e for e in sink.events if e[0] == "stale_feedback"]
    assert len(stale) == 1 and stale[0][1] == injected + 1 and "elbow_joint" in stale[0][2]
    warnings = [e for e in sink.events if e[0] == "warning"]
    assert any("stale_cycles +1" in e[2] for e in warnings), warnings
    assert any("bus_dropped +1" in e[2] for e in warnings), warnings
    status = runtime.status()
    assert status["bus"]["dropped"] == 1 and status["supervisor"]["stale_cycles"] == 1
    json.dumps(status)  # the control socket sends it as JSON


def test_no_warning_when_nothing_rose() -> None:
    runtime, _, sink = _runtime(loop={"stats_interval_s": 1e-6})
    runtime.run(max_cycles=20)
    assert [e for e in sink.events if e[0] in ("warning", "stale_feedback")] == []


def test_a_law_whose_state_went_non_finite_is_policy_nonfinite_not_internal() -> None:
    bundle = StubBundle(state_size=2)
    runtime, bus, sink = _runtime(bundle=bundle)
    runtime.run(max_cycles=3)
    bundle.next_state_value = float("nan")  # the torques stay finite: the law cannot go on all the same
    result = runtime.run(max_cycles=3, stop_on_fault=True)
    assert result.fault is not None, result
    assert result.fault.startswith("policy_nonfinite: the feedback law's next state"), result.fault
    assert bus.quick_stop_calls == 1
    assert sink.events[-1][0] == "fault"


def test_law_substitutions_are_in_stats_and_status() -> None:
    bundle = PolicyBundle.load(PD_BUNDLE)
    runtime, _, _ = _runtime(bundle=bundle)
    runtime.supervisor.law_substitutions = 7
    assert runtime.stats()["law_substitutions"] == 7 and runtime.status()["supervisor"]["law_substitutions"] == 7
    assert "nonfinite_fallbacks" not in runtime.stats()  # one name for one quantity (the supervisor's)


def test_the_record_is_written_whole_or_not_at_all(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    record = RunRecord(4, 6)
    record.add(CycleState.zeros(6), 0.0, 0.0, 0.0)
    path = tmp_path / "run.npz"
    record.save_npz(path)
    with np.load(path) as data:
        assert data["tau"].shape == (1, 6)

    def broken(file: object, **_arrays: object) -> None:
        Path(str(file)).write_bytes(b"PK\x03\x04 half")  # a writer that dies half-way
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez_compressed", broken)
    with pytest.raises(OSError):
        record.save_npz(tmp_path / "other.npz")
    assert sorted(os.listdir(tmp_path)) == ["run.npz"]  # no half file, no temporary left behind
