"""The pacer on a fake clock: absolute deadlines, overruns counted and skipped (never a burst)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil_runtime.pacer import Pacer, Pacing, RollingStats


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        assert seconds > 0
        self.sleeps.append(seconds)
        self.now += seconds


def _pacer(period_s: float = 0.001, pacing: Pacing = "clock") -> tuple[Pacer, FakeClock]:
    clock = FakeClock()
    return Pacer(period_s, pacing, clock=clock, sleep=clock.sleep, stats_window=64), clock


def test_deadlines_are_absolute_so_work_does_not_drift_the_schedule() -> None:
    pacer, clock = _pacer()
    start = pacer.start()
    starts = []
    for k in range(50):
        starts.append(pacer.wait())
        clock.now += 0.0003 + 0.0001 * (k % 3)  # varying work, always under the period
    assert np.allclose(np.array(starts) - start, np.arange(50) * 0.001, atol=1e-12)
    assert pacer.overruns == 0 and pacer.skipped == 0
    assert pacer.tick == 49 and pacer.cycles == 50


def test_an_overrun_is_counted_and_missed_periods_are_skipped_not_run_in_a_burst() -> None:
    pacer, clock = _pacer()
    start = pacer.start()
    pacer.wait()
    clock.now += 0.0035  # the first cycle takes 3.5 periods
    late = pacer.wait()
    assert late == pytest.approx(start + 0.0035)  # starts at once...
    assert pacer.overruns == 1
    assert pacer.skipped == 2  # periods 1 and 2 lie wholly in the past: skipped
    assert pacer.tick == 3  # ...in the slot of period 3, already begun
    clock.now += 0.0001
    nxt = pacer.wait()
    assert nxt == pytest.approx(start + 0.004)  # back on the absolute grid, no catch-up burst
    assert pacer.tick == 4 and pacer.overruns == 1
    assert len(clock.sleeps) == 1


def test_a_slightly_late_cycle_is_an_overrun_without_skipping() -> None:
    pacer, clock = _pacer()
    start = pacer.start()
    pacer.wait()
    clock.now += 0.0012
    pacer.wait()
    assert (pacer.overruns, pacer.skipped, pacer.tick) == (1, 0, 1)
    clock.now += 0.0001
    assert pacer.wait() == pytest.approx(start + 0.002)


def test_bus_pacing_never_sleeps_and_ticks_once_per_cycle() -> None:
    pacer, clock = _pacer(pacing="bus")
    pacer.start()
    for _ in range(10):
        pacer.wait()
        clock.now += 0.0004
    assert clock.sleeps == []
    assert pacer.tick == 9 and pacer.overruns == 0
    assert pacer.summary()["rate_hz"] == pytest.approx(2500.0)


def test_period_statistics() -> None:
    pacer, clock = _pacer()
    pacer.start()
    for k in range(40):
        pacer.wait()
        clock.now += 0.0025 if k == 20 else 0.0002
    summary = pacer.summary()
    assert summary["period_median_s"] == pytest.approx(0.001)
    assert summary["period_max_s"] == pytest.approx(0.0025, rel=1e-6)
    assert summary["overruns"] == 1


def test_rolling_stats_keep_a_window_and_the_all_time_max() -> None:
    stats = RollingStats(window=100)
    assert math.isnan(stats.summary()["median"])
    for v in range(1000):
        stats.add(float(v))
    s = stats.summary()
    assert s["count"] == 1000
    window = np.arange(900, 1000)  # the last 100 samples
    assert s["median"] == np.percentile(window, 50, method="nearest")
    assert s["p99"] == np.percentile(window, 99, method="nearest")
    assert s["max"] == 999.0 and s["max_all"] == 999.0
    stats.add(-1.0)  # overwrites the oldest in place
    assert stats.values().shape == (100,)


def test_invalid_period() -> None:
    with pytest.raises(ValueError):
        Pacer(0.0)


@pytest.mark.parametrize("n", [1, 2, 3, 10, 99, 100, 101, 4096])
def test_percentiles_are_numpys_nearest_rank(n: int) -> None:
    rng = np.random.default_rng(n)
    data = rng.exponential(size=n)
    stats = RollingStats(window=4096)
    for v in data:
        stats.add(float(v))
    s = stats.summary()
    assert s["median"] == np.percentile(data, 50, method="nearest")
    assert s["p99"] == np.percentile(data, 99, method="nearest")
    assert s["max"] == data.max()


class SpinningClock(FakeClock):
    """Each reading of the clock costs 10 µs of it (the spin's polls); sleeps overshoot by 60 µs,
    as a wake-up on a loaded VM does."""

    def __init__(self) -> None:
        super().__init__()
        self.polls = 0

    def __call__(self) -> float:
        self.polls += 1
        self.now += 10e-6
        return self.now

    def sleep(self, seconds: float) -> None:
        super().sleep(seconds)
        self.now += 60e-6


def test_the_hybrid_wait_sleeps_to_spin_s_before_the_deadline_then_spins_onto_it() -> None:
    clock = SpinningClock()
    pacer = Pacer(0.001, "clock", clock=clock, sleep=clock.sleep, spin_s=200e-6)
    pacer.start()
    pacer.wait()
    clock.now += 300e-6  # work: 0.7 ms of slack
    polls = clock.polls
    start = pacer.wait()
    assert clock.sleeps[-1] == pytest.approx(1e-3 - 300e-6 - 200e-6 - 20e-6, abs=1e-9)  # woke 60 µs late...
    assert 0 <= start - (pacer.started_s + 1e-3) < 10e-6 + 1e-9  # ...and spun onto the deadline
    assert clock.polls - polls > 10
    clock.now += 850e-6  # 0.15 ms of slack: too little to sleep, then spin; slept whole (overshoot)
    sleeps = len(clock.sleeps)
    pacer.wait()
    assert len(clock.sleeps) == sleeps + 1 and clock.sleeps[-1] < 150e-6
    with pytest.raises(ValueError, match="spin_s"):
        Pacer(0.001, spin_s=0.001)
