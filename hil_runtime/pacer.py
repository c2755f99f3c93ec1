"""Pacing the loop: absolute deadlines on the monotonic clock, and per-cycle timing statistics.

:class:`Pacer` keeps ``next_s += period_s`` (ros2_control's ``sleep_until``, python-can's periodic
sender): it never drifts, and when a cycle overruns its deadline the missed periods are counted
and skipped, never run in a burst to catch up. ``tick`` counts periods since :meth:`Pacer.start`,
skipped ones included, so a reference indexed by it stays on the wall clock.

Hybrid wait (``spin_s`` > 0): the pacer sleeps until ``spin_s`` before the deadline, then spins on
the clock onto it. A sleep to the deadline wakes late (on this VM a halted vCPU waits for the
host: 17-34 µs median, p99 50-57 µs of the period lost at every cycle's start); the spin starts
the cycle on its deadline (0.1 / 0.2 µs, ``benchmarks/bench_pacer_wake.py``). It does not warm the
policy call: that is cold from what ran on the CPU during the sleep (``bench_policy_cold.py``).
Only for a loop that has a CPU of its own, and only when the slack leaves a sleep of at least
``MIN_SLEEP_S`` first.

With ``pacing="bus"`` the pacer never sleeps: a lock-stepped target answers each SYNC after one
simulated period, so the bus itself paces the loop and ``tick`` advances one per cycle.

:class:`RollingStats` keeps the last ``window`` samples in a fixed ring buffer (one float store per
cycle, nothing allocated) and computes median / p99 / max on demand (about 1 Hz), plus the
all-time max and count.

The clock and the sleep are injectable, so the unit tests run the pacer on a fake clock.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Literal

import numpy as np

Pacing = Literal["clock", "bus"]

# The hybrid wait spins only after a sleep of at least this long: a SCHED_FIFO loop that never
# sleeps starves the other tasks of its CPU, and the kernel then takes the CPU from it (RT
# throttling, the fair server: up to 50 ms a second), a stall far past any overrun budget.
MIN_SLEEP_S = 100e-6


class RollingStats:
    """Median, p99 and max over the last ``window`` samples; all-time max and count."""

    def __init__(self, window: int = 4096) -> None:
        if window < 1:
            raise ValueError("window must be at least 1")
        self._buf = np.zeros(window)
        self._scratch = np.zeros(window)  # summary() partitions a copy here: nothing allocated
        self._window = window
        self._i = 0
        self.count = 0
        self.max_all = 0.0

    def add(self, value: float) -> None:
        self._buf[self._i] = value
        self._i += 1
        if self._i == self._window:
            self._i = 0
        self.count += 1
        self.max_all = max(self.max_all, value)

    def reset(self) -> None:
        self._i = 0
        self.count = 0
        self.max_all = 0.0

    def values(self) -> np.ndarray:
        """The samples in the window (a copy, oldest order not kept)."""
        return self._buf[: min(self.count, self._window)].copy()

    def summary(self) -> dict[str, float]:
        """{median, p99, max} over the window (max_all: since reset); NaN when empty.

        Nearest-rank percentiles (numpy's ``method="nearest"``) from one ``partition`` of a copy:
        ~40 µs for 4096 samples where ``np.percentile`` takes ~160 µs; the loop calls it about
        once a second.
        """
        n = min(self.count, self._window)
        if n == 0:
            return {"median": math.nan, "p99": math.nan, "max": math.nan, "max_all": math.nan, "count": 0}
        data = self._scratch[:n]
        data[:] = self._buf[:n]
        k50, k99 = int(np.rint(0.5 * (n - 1))), int(np.rint(0.99 * (n - 1)))
        data.partition((k50, k99))
        return {
            "median": float(data[k50]),
            "p99": float(data[k99]),
            "max": float(data[k99:].max()),
            "max_all": self.max_all,
            "count": self.count,
        }


class Pacer:
    """Absolute-deadline pacing with overrun accounting (see the module docstring)."""

    def __init__(
        self,
        period_s: float,
        pacing: Pacing = "clock",
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        stats_window: int = 4096,
        spin_s: float = 0.0,
    ) -> None:
        if not period_s > 0:
            raise ValueError("period_s must be positive")
        if not 0.0 <= spin_s < period_s:
            raise ValueError("spin_s must be in [0, period_s)")
        self.period_s = period_s
        self.spin_s = spin_s  # hybrid wait: the last stretch before a deadline spun, not slept
        self.pacing = pacing
        self._clock = clock
        self._sleep = sleep
        self.tick = 0  # periods since start(), skipped ones included
        self.cycles = 0  # cycles actually run
        self.overruns = 0  # cycles that started after their deadline (the one before ran too long)
        self.skipped = 0  # periods skipped because of overruns
        # Periods in a row without an on-time start: each overrun and the periods it skipped (0
        # when this cycle started on time); the supervisor's overrun budget reads it.
        self.late_run = 0
        self.started_s = 0.0
        self._next_s = 0.0
        self._last_start_s = math.nan
        self.period_stats = RollingStats(stats_window)  # start-to-start, seconds
        self.compute_stats = RollingStats(stats_window)  # loop work per cycle, seconds
        self.exchange_stats = RollingStats(stats_window)  # waiting on the bus per cycle, seconds

    def start(self) -> float:
        """Arm the pacer: the first cycle starts now, tick 0."""
        now = self._clock()
        self.started_s = now
        self._next_s = now
        self._last_start_s = math.nan
        self.tick = 0
        self.cycles = 0
        self.overruns = 0
        self.skipped = 0
        self.late_run = 0
        for stats in (self.period_stats, self.compute_stats, self.exchange_stats):
            stats.reset()
        return now

    def wait(self) -> float:
        """Block until this cycle's deadline; returns the cycle's start time (clock seconds).

        Clock pacing: when the previous cycle ran past this cycle's deadline, that is an overrun;
        this cycle starts at once, in the latest period slot already begun, and the periods wholly
        past are skipped (``tick`` jumps over them), so the loop never runs a burst of late cycles.
        """
        clock = self._clock
        if self.cycles == 0:
            now = clock()
        elif self.pacing == "bus":
            now = clock()
            self.tick += 1
        else:
            deadline = self._next_s + self.period_s
            now = clock()
            if now < deadline:
                spin_s = self.spin_s
                if spin_s > 0.0 and deadline - now > spin_s + MIN_SLEEP_S:
                    # Hybrid wait: sleep, then spin onto the deadline (no late wake-up).
                    self._sleep(deadline - now - spin_s)
                    now = clock()
                    while now < deadline:
                        now = clock()
                else:  # no spin, or too little slack to sleep before spinning: sleep it all
                    self._sleep(deadline - now)
                    now = clock()
                self.tick += 1
                self._next_s = deadline
                self.late_run = 0
            else:  # the last cycle ran past this deadline: an overrun
                late = int((now - deadline) // self.period_s)  # whole periods already past: skipped
                self.overruns += 1
                self.skipped += late
                self.tick += 1 + late
                self.late_run += 1 + late
                self._next_s = deadline + late * self.period_s
        if self.cycles > 0:
            self.period_stats.add(now - self._last_start_s)
        self._last_start_s = now
        self.cycles += 1
        return now

    @property
    def elapsed_s(self) -> float:
        return self._clock() - self.started_s

    def achieved_rate_hz(self) -> float:
        """Cycles per second over the last window (median period), NaN before two cycles."""
        median = self.period_stats.summary()["median"]
        return 1.0 / median if median and median > 0 else math.nan

    def summary(self) -> dict[str, float]:
        """What telemetry's ``stats`` and the benchmark report: seconds, counts."""
        elapsed = max(self._last_start_s - self.started_s, 0.0) if self.cycles > 1 else 0.0
        out: dict[str, float] = {
            "cycles": self.cycles,
            "tick": self.tick,
            "overruns": self.overruns,
            "skipped_periods": self.skipped,
            "rate_hz": (self.cycles - 1) / elapsed if elapsed > 0 else math.nan,
        }
        for name, stats in (
            ("period", self.period_stats),
            ("compute", self.compute_stats),
            ("exchange", self.exchange_stats),
        ):
            for key, value in stats.summary().items():
                if key != "count":
                    out[f"{name}_{key}_s"] = value  # e.g. period_median_s, compute_p99_s
        return out
