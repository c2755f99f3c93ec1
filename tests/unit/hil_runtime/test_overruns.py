"""Overruns are survivable (docs/runtime.md, "Overruns"): late periods injected into a running loop
with the PD bundle in fb and lmpc modes on a plant that moves on the loop's (fake) clock; past the
overrun budget, a quick stop and FAULT overrun_budget, never a crash."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from drivers.feedback import DriveFeedback
from drivers.testing import FakeJointBus
from hil_runtime.config import parse_runtime_config
from hil_runtime.lifecycle import LifecycleState
from hil_runtime.runtime import Runtime
from sim_target.testing.ur5 import MAX_TORQUE_NM, Q0_RAD
from tests.unit.hil_runtime.support import config_dict, model_plant
from tests.unit.hil_runtime.test_runtime_loop import INERTIA, RecordingSink

PERIOD_S = 0.001
CYCLES = 1500
LATE_S = 1.5 * PERIOD_S  # a late cycle's work: the next one starts half a period (or more) late
ON_TIME_S = 0.2 * PERIOD_S
# Largest position difference from the on-time run allowed: the law runs at its fixed period and
# the reference on the wall clock, so a late period costs a small, bounded tracking error.
TRACKING_BOUND_RAD = 0.002


class FakeClock:
    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s

    def sleep(self, seconds: float) -> None:
        self.now_s += max(seconds, 0.0)


class WallClockPlantBus(FakeJointBus):
    """The plant moves on the clock: from one SYNC (exchange) to the next, however far apart, the
    drives apply the last set-point (CiA 402 holds it through a late SYNC); the feedback is the
    state at the SYNC. Each cycle's work takes ``work_s(cycle)`` of the clock."""

    def __init__(self, clock: FakeClock, work_s: Callable[[int], float]) -> None:
        super().__init__(
            6, period_s=PERIOD_S, inertia_kgm2=INERTIA, max_torque_nm=MAX_TORQUE_NM, initial_position_rad=Q0_RAD
        )
        self.clock = clock
        self.work_s = work_s
        self.dynamics = model_plant()
        self.plant = lambda q, qd, tau, dt: (q, qd)  # the fake's own per-exchange step: time moves here instead
        self._last_s: float | None = None
        self.held_periods = 0  # SYNC intervals longer than a period

    def _cycle_internal(self, setpoint_nm: np.ndarray) -> DriveFeedback:
        now = self.clock()
        if self._last_s is not None and now > self._last_s:
            elapsed = now - self._last_s
            self.position_rad, self.velocity_rad_s = self.dynamics(
                self.position_rad, self.velocity_rad_s, self.applied_torque_nm, elapsed
            )
            self.held_periods += elapsed > 1.01 * self.period_s
        self._last_s = now
        feedback = super()._cycle_internal(setpoint_nm)
        self.clock.now_s += self.work_s(self._cycle)
        return feedback


def _run(mode: str, work_s: Callable[[int], float], **safety: Any) -> tuple[Runtime, WallClockPlantBus, Any]:
    clock = FakeClock()
    bus = WallClockPlantBus(clock, work_s)
    config = parse_runtime_config(
        config_dict(
            bundle={"mode": mode},
            reference={"kind": "condition", "condition": "C1", "ramp_s": 0.5},
            loop={"pacing": "clock", "warmup_cycles": 2},
            safety=safety,
        ),
        "rt.yaml",
    )
    rt = Runtime(config, bus, record_cycles=CYCLES + 1, telemetry=RecordingSink(), clock=clock, sleep=clock.sleep)
    rt.configure()
    assert rt.activate()
    result = rt.run(max_cycles=CYCLES, stop_on_fault=True)
    return rt, bus, result


def _by_period(rt: Runtime) -> dict[int, np.ndarray]:
    rec = rt.record.arrays()
    return {round(t / PERIOD_S): q for t, q in zip(rec["t_s"], rec["q"], strict=True)}


@functools.cache
def _on_time(mode: str) -> dict[int, np.ndarray]:
    rt, _, result = _run(mode, lambda cycle: ON_TIME_S)
    assert result.reason == "cycles" and rt.pacer.overruns == 0
    return _by_period(rt)


def _single(cycle: int) -> float:
    return LATE_S if cycle % 97 == 0 else ON_TIME_S


def _bursts(cycle: int) -> float:
    length = 2 + (cycle // 211) % 4  # bursts of 2, 3, 4, 5 late cycles, one every 211 cycles
    return LATE_S if cycle % 211 < length else ON_TIME_S


_RANDOM_LATE = np.random.default_rng(21).random(4 * CYCLES) < 0.10


def _random(cycle: int) -> float:
    return LATE_S if _RANDOM_LATE[cycle] else ON_TIME_S


@pytest.mark.parametrize("mode", ["fb", "lmpc"])
@pytest.mark.parametrize("pattern", [_single, _bursts, _random], ids=["single", "bursts_2_5", "random_10pct"])
def test_late_periods_neither_fault_nor_move_the_arm_off_the_on_time_run(
    mode: str, pattern: Callable[[int], float]
) -> None:
    reference = _on_time(mode)
    late, bus, result = _run(mode, pattern)
    assert result.reason == "cycles" and result.state is LifecycleState.ACTIVE, result.fault
    assert late.pacer.overruns > 0 and bus.held_periods > 0  # the pattern did make periods late
    measured = _by_period(late)
    common = sorted(set(reference) & set(measured))
    assert len(common) > CYCLES // 2
    deviation = max(float(np.abs(measured[k] - reference[k]).max()) for k in common)
    assert deviation < TRACKING_BOUND_RAD, f"{deviation:.4f} rad from the on-time run"


def test_late_periods_past_the_budget_quick_stop_and_fault_overrun_budget() -> None:
    # From cycle 500 every cycle takes 1.5 periods: the late run grows past the budget of 20.
    rt, bus, result = _run("fb", lambda cycle: LATE_S if cycle >= 500 else ON_TIME_S, overrun_budget=20)
    assert result.reason == "fault" and result.state is LifecycleState.FAULT
    assert rt.last_fault is not None and rt.last_fault.kind.value == "overrun_budget"
    assert result.fault is not None and "budget 20" in result.fault
    assert bus.quick_stop_calls == 1 and not bus.enabled
    sink = rt.telemetry
    assert isinstance(sink, RecordingSink)
    assert ("FAULT", result.fault) in sink.statuses
    assert any(kind == "fault" and detail.startswith("overrun_budget") for kind, _, detail in sink.events)
    assert 500 < rt.total_cycles < 530  # about budget / 1.5 late cycles after the first one


def test_one_long_stall_is_past_the_budget() -> None:
    # Bus cycle 300 (the 299th exchange: enable was the first) takes 50 periods.
    rt, bus, result = _run("lmpc", lambda cycle: 0.05 if cycle == 300 else ON_TIME_S)
    assert result.reason == "fault" and rt.last_fault is not None
    assert rt.last_fault.kind.value == "overrun_budget" and rt.total_cycles == 299  # no exchange after it
