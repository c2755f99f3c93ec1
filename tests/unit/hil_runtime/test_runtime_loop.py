"""The runtime's loop on a fake joint bus: tracking, faults -> quick stop + FAULT, reset, stop from
another thread, fb mode, the record, the applied-torque state, and what telemetry is handed."""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
import pytest

from drivers.cia402.state_machine import State
from drivers.errors import DriveError, DriveFaultError, FeedbackTimeoutError, HeartbeatLostError
from drivers.feedback import DriveFeedback
from drivers.testing import FakeJointBus
from hil_runtime.bundle import PolicyBundle
from hil_runtime.config import parse_runtime_config
from hil_runtime.lifecycle import LifecycleState
from hil_runtime.runtime import Runtime
from hil_runtime.telemetry.codec import STATS_FIELDS
from hil_runtime.telemetry.sink import CycleState, NullTelemetry
from sim_target.testing.ur5 import MAX_TORQUE_NM, Q0_RAD
from tests.unit.hil_runtime.support import INERTIA, NO_OVERRUN_BUDGET, StubBundle, config_dict, model_plant


def _bus(**kwargs: Any) -> FakeJointBus:
    return FakeJointBus(
        6,
        period_s=0.001,
        inertia_kgm2=INERTIA,
        max_torque_nm=MAX_TORQUE_NM,
        initial_position_rad=Q0_RAD,
        **kwargs,
    )


class RecordingSink(NullTelemetry):
    def __init__(self) -> None:
        self.calls: list[str] = []
        self.statuses: list[tuple[str, str | None]] = []
        self.events: list[tuple[str, int, str]] = []
        self.states = 0
        self.stats: list[dict[str, float]] = []

    def start(self) -> None:
        self.calls.append("start")

    def offer_state(self, sample: CycleState) -> None:
        self.states += 1
        assert isinstance(sample, CycleState) and sample.q.shape == sample.tau.shape == (6,)

    def offer_stats(self, stats: Mapping[str, float]) -> None:
        self.stats.append(dict(stats))

    def set_status(self, state: str, fault: str | None) -> None:
        self.statuses.append((state, fault))

    def event(self, kind: str, cycle: int, detail: str) -> None:
        self.events.append((kind, cycle, detail))

    def close(self) -> None:
        self.calls.append("close")


def _sink(rt: Runtime) -> RecordingSink:
    """The runtime's telemetry as the recording stand-in _runtime gave it."""
    assert isinstance(rt.telemetry, RecordingSink)
    return rt.telemetry


def _runtime(bus: FakeJointBus, record: int = 0, bundle: PolicyBundle | None = None, **overrides: Any) -> Runtime:
    config = parse_runtime_config(config_dict(**overrides), "rt.yaml")
    return Runtime(config, bus, record_cycles=record, bundle=bundle, telemetry=RecordingSink())


def test_pd_bundle_ramps_onto_c1_and_tracks_it_inside_the_limits() -> None:
    bus = _bus(plant=model_plant())
    rt = _runtime(bus, record=8000, reference={"kind": "condition", "condition": "C1", "ramp_s": 1.0})
    rt.configure()
    assert rt.state is LifecycleState.INACTIVE and bus.events == ["connect"]
    assert rt.activate()
    ramp = rt.reference.ramp_cycles
    assert ramp >= 1000
    result = rt.run(max_cycles=ramp + 5000)
    assert result.reason == "cycles" and result.state is LifecycleState.ACTIVE
    rec = rt.record.arrays()
    assert rec["q"].shape == (ramp + 5001, 6)  # the activation row + every cycle
    # The reference starts at the measured pose (no step) and reaches C1's start at the ramp's end.
    np.testing.assert_allclose(rec["q_ref"][0], rec["q"][0], atol=1e-12)
    np.testing.assert_allclose(rec["qd_ref"][0], 0.0, atol=1e-12)
    steps = np.abs(np.diff(rec["q_ref"], axis=0)).max()
    assert steps < 3e-3, f"reference step {steps}"
    np.testing.assert_allclose(rec["t_s"][:3], [0.0, 0.001, 0.002])
    tracking = np.abs(rec["q"] - rec["q_ref"])[ramp:].max()
    assert tracking < 0.3
    assert np.all(np.abs(rec["tau"]) <= np.array(MAX_TORQUE_NM) + 1e-9)
    assert np.all(np.abs(rec["q"]) <= np.pi)
    # The torque chosen in each row is what the next exchange sent (row 0: from enable's feedback).
    assert len(bus.commands) == ramp + 5000
    np.testing.assert_allclose(np.array(bus.commands), rec["tau"][:-1], atol=1e-12)
    assert np.all(rec["compute_s"][1:] > 0)
    rt.shutdown()
    assert rt.state is LifecycleState.FINALIZED
    assert bus.events[-3:] == ["quick_stop", "disable", "close"]
    assert _sink(rt).calls == ["start", "close"]
    assert [s for s, _ in _sink(rt).statuses] == ["INACTIVE", "ACTIVE", "FINALIZED"]


def test_a_second_run_goes_on_along_the_reference() -> None:
    rt = _runtime(_bus(), record=100, reference={"kind": "condition", "condition": "C1", "ramp_s": 0.5})
    rt.configure()
    rt.activate()
    rt.run(max_cycles=30)
    rt.run(max_cycles=30)
    np.testing.assert_allclose(np.diff(rt.record.t_s[: rt.record.n]), 0.001)


@pytest.mark.parametrize(
    ("error", "kind"),
    [
        (FeedbackTimeoutError((3,), 2), "feedback_timeout"),
        (HeartbeatLostError(5, "no heartbeat for 0.3 s"), "heartbeat_lost"),
        (DriveFaultError(4, 0x2310, "EMCY"), "drive_fault"),
    ],
)
def test_a_driver_error_is_a_fault_drives_stopped_daemon_up_until_reset(error: DriveError, kind: str) -> None:
    bus = _bus()
    rt = _runtime(bus, loop={"pacing": "bus", "idle_poll_s": 0.001})
    rt.configure()
    rt.activate()
    rt.run(max_cycles=20)
    bus.fail_next_exchange(error)
    result = rt.run(max_cycles=20, stop_on_fault=True)
    assert result.reason == "fault" and result.state is LifecycleState.FAULT
    assert result.fault is not None and result.fault.startswith(kind)
    assert rt.last_fault is not None and rt.last_fault.kind.value == kind
    assert result.fault_cycle == 21  # the 21st exchange raised: acted on in that very cycle
    assert not bus.enabled and bus.fail_safe_count == 1 and bus.quick_stop_calls >= 1
    assert ("fault", 21, result.fault) in _sink(rt).events
    # FAULT: the loop thread waits for a reset; then ACTIVE again from the measured pose.
    done = threading.Event()
    outcome = {}

    def loop() -> None:
        outcome["result"] = rt.run()
        done.set()

    thread = threading.Thread(target=loop)
    thread.start()
    time.sleep(0.05)
    assert rt.state is LifecycleState.FAULT and not done.is_set()
    rt.request_reset()
    deadline = time.monotonic() + 5
    while rt.state is not LifecycleState.ACTIVE and time.monotonic() < deadline:
        time.sleep(0.005)
    assert rt.state is LifecycleState.ACTIVE
    assert "fault_reset" in bus.events and bus.enabled
    rt.request_stop()
    thread.join(5)
    assert done.is_set() and outcome["result"].reason == "stop"
    rt.shutdown()
    assert bus.states == (State.SWITCH_ON_DISABLED,) * 6


def test_stale_feedback_faults_within_two_cycles() -> None:
    bus = _bus(max_missed_cycles=1000)  # the bus tolerates it: the supervisor must not
    rt = _runtime(bus)
    rt.configure()
    rt.activate()
    rt.run(max_cycles=10)
    bus.make_stale([2], cycles=5)
    before = len(bus.commands)
    result = rt.run(max_cycles=10, stop_on_fault=True)
    assert result.fault is not None and result.fault.startswith("stale_feedback")
    assert len(bus.commands) - before == 2
    assert bus.quick_stop_calls == 1 and not bus.enabled


def test_leaving_the_position_limits_quick_stops_and_faults() -> None:
    def runaway(q: np.ndarray, qd: np.ndarray, tau: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        qd = qd.copy()
        qd[1] = -2.0  # something drags joint 2 down faster than any command
        return q + qd * dt, qd

    bus = FakeJointBus(
        6,
        period_s=0.001,
        plant=runaway,
        max_torque_nm=MAX_TORQUE_NM,
        initial_position_rad=(0.0, -2.0, 0.0, 0.0, 0.0, 0.0),
    )
    rt = _runtime(bus, record=2000)
    rt.configure()
    rt.activate()
    result = rt.run(max_cycles=2000, stop_on_fault=True)
    assert result.fault is not None and result.fault.startswith("position_limit: shoulder_lift_joint")
    lower = -2.5132741228718345  # the bundle manifest's limit
    assert rt.record.q[rt.record.n - 1, 1] >= lower  # every recorded sample inside the limits
    assert bus.position_rad[1] < lower + 0.003  # the fault came at the first sample beyond it
    assert bus.quick_stop_calls == 1


def test_non_finite_policy_output_falls_back_to_the_law_then_faults_when_both_are_bad() -> None:
    bundle = StubBundle()
    bus = _bus()
    rt = _runtime(bus, bundle=bundle)
    rt.configure()
    rt.activate()
    rt.run(max_cycles=5)
    bundle.tau_value = np.full(6, np.nan)
    rt.run(max_cycles=5)
    assert rt.state is LifecycleState.ACTIVE
    assert rt.supervisor.law_substitutions == 5
    assert np.isfinite(np.array(bus.commands)).all()
    bundle.tau_fb_value = np.full(6, np.inf)
    result = rt.run(max_cycles=5, stop_on_fault=True)
    assert result.fault is not None and result.fault.startswith("policy_nonfinite")
    assert bus.quick_stop_calls == 1


def test_an_exception_inside_the_loop_is_a_fault_not_a_crash() -> None:
    bundle = StubBundle()
    bus = _bus()
    rt = _runtime(bus, bundle=bundle)
    rt.configure()
    rt.activate()

    def broken() -> None:
        raise ZeroDivisionError("bug")

    bundle.before_step = broken
    result = rt.run(max_cycles=5, stop_on_fault=True)
    assert result.fault == "internal: ZeroDivisionError: bug"
    assert bus.quick_stop_calls == 1


def test_fb_mode_commands_the_law_torque_and_the_state_records_it() -> None:
    bundle = StubBundle(state_size=8, applied=[2, 8])
    bundle.tau_value = np.full(6, 7.0)  # what lmpc would command
    bus = _bus()
    config = parse_runtime_config(config_dict(bundle={"path": "unused", "mode": "fb"}), "rt.yaml")
    rt = Runtime(config, bus, bundle=bundle)
    rt.configure()
    rt.activate()
    rt.run(max_cycles=3)
    sent = np.array(bus.commands)
    assert not np.allclose(sent, 7.0)  # the law's torque, not the policy's
    # The next state's applied-torque slot holds what was commanded; the rest is the graph's.
    state = rt.controller.state
    np.testing.assert_allclose(state[2:8], rt.pipeline.command)
    assert state[0] == pytest.approx(bundle.states_seen[-1][0] + 1.0)


def test_request_stop_from_another_thread_ends_the_loop_promptly() -> None:
    bus = _bus()
    rt = _runtime(bus, loop={"pacing": "clock"}, safety=NO_OVERRUN_BUDGET)
    rt.configure()
    rt.activate()
    timer = threading.Timer(0.2, rt.request_stop)
    timer.start()
    t0 = time.monotonic()
    result = rt.run(shutdown_at_end=True)
    assert time.monotonic() - t0 < 5.0  # generous: the machine may be loaded; the loop itself answers in a cycle
    assert result.reason == "stop" and rt.state is LifecycleState.FINALIZED
    pacer = rt.pacer
    assert result.cycles >= 10
    assert pacer.tick == pacer.cycles - 1 + pacer.skipped  # clock pacing: every period slot accounted for
    assert bus.events[-3:] == ["quick_stop", "disable", "close"]


def test_duration_ends_the_run_and_stats_carry_the_telemetry_fields() -> None:
    rt = _runtime(_bus(), loop={"pacing": "bus", "duration_s": 0.2, "stats_interval_s": 0.05})
    rt.configure()
    rt.activate()
    result = rt.run()
    assert result.reason == "duration" and result.cycles == 200  # 200 exchanges: the arm reached period 200 = 0.2 s
    stats = result.stats
    # Every stats field of the telemetry schema but the two the sink fills itself.
    for name in (f for f in STATS_FIELDS if not f.startswith("telemetry_")):
        assert name in stats, name
    assert _sink(rt).states == 201  # the activation row + one per exchange
    assert _sink(rt).stats


def test_status_snapshot_is_json_able() -> None:
    import json

    rt = _runtime(_bus())
    rt.configure()
    rt.activate()
    rt.run(max_cycles=50)
    status = json.loads(json.dumps(rt.status()))
    assert status["state"] == "ACTIVE" and status["cycles"] == 50 and status["fault"] is None


@pytest.mark.parametrize(("time_base", "expect_jumps"), [("wall", True), ("cycles", False), ("auto", True)])
def test_overruns_move_the_reference_on_wall_time_but_not_on_cycles(time_base: str, expect_jumps: bool) -> None:
    """Clock pacing on a fake clock; every 10th exchange takes 2.5 periods (an overrun, two periods
    skipped). On wall time the reference index jumps over the skipped periods; on cycles (a lock-
    stepped target) it advances one row per exchange."""
    now = [0.0]

    class SlowBus(FakeJointBus):
        calls = 0

        def _cycle_internal(self, setpoint_nm: np.ndarray) -> DriveFeedback:  # both cycle kinds
            self.calls += 1
            now[0] += 0.0025 if self.calls % 10 == 0 else 0.0002
            return super()._cycle_internal(setpoint_nm)

    bus = SlowBus(6, period_s=0.001, inertia_kgm2=INERTIA, max_torque_nm=MAX_TORQUE_NM, initial_position_rad=Q0_RAD)
    config = parse_runtime_config(
        config_dict(loop={"pacing": "clock", "time_base": time_base}, safety=NO_OVERRUN_BUDGET), "rt.yaml"
    )
    rt = Runtime(config, bus, record_cycles=200, clock=lambda: now[0], sleep=lambda s: now.__setitem__(0, now[0] + s))
    rt.configure()
    rt.activate()
    rt.run(max_cycles=101)  # the 10th slow exchange's overrun shows at the 101st cycle's start
    steps = np.round(np.diff(rt.record.t_s[: rt.record.n]) / 0.001).astype(int)
    assert rt.pacer.overruns == 10 and rt.pacer.skipped == 10
    if expect_jumps:
        assert sorted(set(steps.tolist())) == [1, 2] and (steps == 2).sum() == 10
    else:
        assert set(steps.tolist()) == {1}


def test_activate_outside_inactive_never_touches_the_drives() -> None:
    from hil_runtime.lifecycle import LifecycleError

    bus = _bus()
    rt = _runtime(bus)
    with pytest.raises(LifecycleError, match="cannot activate from UNCONFIGURED"):
        rt.activate()
    assert bus.events == []
    rt.configure()
    with pytest.raises(LifecycleError, match="cannot configure from INACTIVE"):
        rt.configure()
    rt.activate()
    bus.fail_next_exchange(DriveFaultError(2, 0x2310, "EMCY"))
    rt.run(max_cycles=5, stop_on_fault=True)
    enables = bus.events.count("enable")
    with pytest.raises(LifecycleError, match="cannot activate from FAULT"):
        rt.activate()
    assert bus.events.count("enable") == enables


def test_a_reset_requested_before_a_fault_does_not_clear_it() -> None:
    bus = _bus()
    rt = _runtime(bus, loop={"pacing": "bus", "idle_poll_s": 0.001})
    rt.configure()
    rt.activate()
    rt.request_reset()  # while healthy: meaningless, and must not linger
    rt.request_activate()
    rt.run(max_cycles=5)
    bus.fail_next_exchange(DriveFaultError(2, 0x2310, "EMCY"))
    rt.run(max_cycles=5, stop_on_fault=True)
    timer = threading.Timer(0.1, rt.request_stop)
    timer.start()
    result = rt.run()  # waits in FAULT until stopped: nothing resets it
    assert result.state is LifecycleState.FAULT and "fault_reset" not in bus.events


def test_the_condition_table_is_built_before_the_drives_are_enabled(monkeypatch: pytest.MonkeyPatch) -> None:
    # An hour's table takes ~1.6 s at 1 kHz: built after enable, the drives wait at zero torque that
    # long and fault. Every call of the condition's reference over many rows must come before enable.
    from hil_runtime.conditions import Condition

    bus = _bus()
    rt = _runtime(bus, reference={"kind": "condition", "condition": "C1", "ramp_s": 0.1})
    evaluate = Condition.reference
    tables: list[bool] = []

    def spy(self: Condition, t_s: Any) -> Any:
        if np.size(t_s) > 100:
            tables.append(bus.enabled)
        return evaluate(self, t_s)

    monkeypatch.setattr(Condition, "reference", spy)
    rt.configure()
    assert rt.activate()
    assert tables == [False]  # one table, built while the drives were still disabled
    rt.run(max_cycles=10)
    assert tables == [False]  # the run reads rows; it builds none
    rt.shutdown()


@pytest.mark.parametrize("exchange", ["auto", "overlap", "wait"])
def test_clock_pacing_overlaps_cycles_unless_told_to_wait(exchange: str) -> None:
    """Clock pacing (auto, overlap): each cycle collects the feedback of the SYNC the cycle before
    sent, computes, sends; the first only sends the set-point computed at activation. Waiting
    cycles call exchange(). Either way the reference rows run on, one per period, from row 1."""
    now = [0.0]
    calls: list[str] = []

    class CountingBus(FakeJointBus):
        def exchange(self, torque_nm: np.ndarray) -> DriveFeedback:
            calls.append("exchange")
            return super().exchange(torque_nm)

        def send(self, torque_nm: np.ndarray) -> None:
            calls.append("send")
            super().send(torque_nm)

        def collect(self) -> DriveFeedback:
            calls.append("collect")
            return super().collect()

    bus = CountingBus(6, period_s=0.001, inertia_kgm2=INERTIA, max_torque_nm=MAX_TORQUE_NM, initial_position_rad=Q0_RAD)
    config = parse_runtime_config(config_dict(loop={"pacing": "clock", "exchange": exchange}), "rt.yaml")
    rt = Runtime(config, bus, record_cycles=200, clock=lambda: now[0], sleep=lambda s: now.__setitem__(0, now[0] + s))
    rt.configure()
    rt.activate()
    calls.clear()
    rt.run(max_cycles=50)
    rows = np.round(rt.record.t_s[: rt.record.n] / 0.001).astype(int)
    if exchange == "wait":
        assert calls == ["exchange"] * 50
        assert rows.tolist() == list(range(51))
    else:
        assert calls == ["send"] + ["collect", "send"] * 49 + ["collect"]  # the last SYNC closed at the end
        assert rows.tolist() == list(range(50))  # row 0 at activation, then one per computing cycle
    assert rt.lifecycle.state is LifecycleState.ACTIVE and bus.enabled
