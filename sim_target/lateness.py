"""How far the free-running target fell behind the wall clock, and when that voids a HIL run.

A free-running target (``clock: realtime``) steps its physics once per tick of a monotonic clock
with absolute deadlines. A tick that wakes late publishes a state older than the wall clock says;
a tick whose step runs past the next deadline makes the target drop the periods already past
(never run in a burst), and simulated time then runs slower than the wall clock the runtime's
reference runs on. A HIL run in which that happened is no longer a test of the controller: it is
marked invalid (:func:`invalid_reason`) and its scores are not reported as valid.

Counted per run (reset by each run start, ``{"kind": "start"}``) and in total since the target
started; both are in the target's status (``hil target inject --socket S '{"kind": "status"}'``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

# A run is invalid when its plant skipped more than this fraction of its periods ...
MAX_SKIPPED_FRACTION = 1e-3
# ... or when a tick started more than this many periods behind its deadline.
MAX_LAG_PERIODS = 1.0


@dataclass
class Lateness:
    """One window's lateness of the physics clock (all zero in lock-step: no wall clock to lag)."""

    periods: int = 0  # periods of wall time covered (stepped + skipped)
    late_ticks: int = 0  # ticks whose step ran past the next deadline
    skipped_periods: int = 0  # periods dropped to catch up, never run in a burst
    worst_lag_s: float = 0.0  # the latest a tick started after its deadline
    # time.thread_time() / time.monotonic() at the window's start: the loop thread's CPU share
    started_cpu_s: float = 0.0
    started_wall_s: float = 0.0

    @classmethod
    def starting_now(cls) -> Lateness:
        """A window opened by the loop thread (whose CPU time it will report)."""
        return cls(started_cpu_s=time.thread_time(), started_wall_s=time.monotonic())

    def tick(self, lag_s: float, missed: int) -> None:
        self.periods += 1 + missed
        if missed:
            self.late_ticks += 1
            self.skipped_periods += missed
        if lag_s > self.worst_lag_s:
            self.worst_lag_s = lag_s

    def as_dict(self, period_s: float) -> dict[str, Any]:
        """For the status; called on the loop thread (``cpu_fraction`` is that thread's CPU time,
        physics and bus together, over the wall time of the window)."""
        wall_s = time.monotonic() - self.started_wall_s
        cpu_s = time.thread_time() - self.started_cpu_s
        return {
            "periods": self.periods,
            "late_ticks": self.late_ticks,
            "skipped_periods": self.skipped_periods,
            "skipped_fraction": self.skipped_periods / self.periods if self.periods else 0.0,
            "worst_lag_s": round(self.worst_lag_s, 6),
            "worst_lag_periods": round(self.worst_lag_s / period_s, 3),
            "cpu_fraction": round(cpu_s / wall_s, 4) if wall_s > 0 else 0.0,
            "wall_s": round(wall_s, 3),
        }


def invalid_reason(lateness: dict[str, Any] | None, period_s: float) -> str | None:
    """Why a run with this ``lateness`` (:meth:`Lateness.as_dict`, from the target's status) is not
    a valid HIL run, or None when the plant kept real time. An unknown lateness is not a reason."""
    if not lateness:
        return None
    periods = int(lateness.get("periods", 0))
    skipped = int(lateness.get("skipped_periods", 0))
    lag_s = float(lateness.get("worst_lag_s", 0.0))
    reasons = []
    if periods and skipped / periods > MAX_SKIPPED_FRACTION:
        reasons.append(
            f"the plant skipped {skipped} of {periods} periods ({100 * skipped / periods:.2f} % > "
            f"{100 * MAX_SKIPPED_FRACTION:g} %)"
        )
    if lag_s > MAX_LAG_PERIODS * period_s:
        reasons.append(f"the plant lagged the wall clock by {lag_s * 1e3:.2f} ms (> {MAX_LAG_PERIODS:g} period)")
    return "; ".join(reasons) or None


__all__ = ["MAX_LAG_PERIODS", "MAX_SKIPPED_FRACTION", "Lateness", "invalid_reason"]
