"""What the runtime reports about itself: the anomaly counters it rides through and how their
rises become ``warning`` events, and the helpers that turn counters into JSON-able numbers."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from hil_runtime.runtime import Runtime

# Counters of anomalies the loop rides through; a rise is reported as a ``warning`` telemetry event.
WARNING_COUNTERS = (
    "overruns",
    "skipped_periods",
    "law_substitutions",
    "saturations",
    "stale_cycles",
    "bus_dropped",
    "bus_late",
    "bus_malformed",
    "bus_unknown_cob_id",
    "bus_emcy",
)


class CounterRises:
    """The WARNING_COUNTERS that rose since the last look: one ``warning`` line per stats interval."""

    def __init__(self) -> None:
        self._seen: dict[str, Any] = {}

    def since_last(self, stats: Mapping[str, Any]) -> str | None:
        """``"overruns +3, bus_late +1"`` for the counters that rose, None when none did."""
        seen = self._seen
        rose = [
            f"{name} +{stats[name] - seen.get(name, 0)}"
            for name in WARNING_COUNTERS
            if stats.get(name, 0) > seen.get(name, 0)
        ]
        self._seen = {name: stats.get(name, 0) for name in WARNING_COUNTERS}
        return ", ".join(rose) if rose else None


def counters_dict(counters: object) -> dict[str, Any]:
    """The bus's counters (a dataclass instance, JointBus.counters) as a dict; {} for anything else."""
    if dataclasses.is_dataclass(counters) and not isinstance(counters, type):
        return dataclasses.asdict(counters)
    return {}


def finite(value: Any) -> float | None:
    """``value`` as a float when it is a finite number, else None (JSON has no NaN)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) else None


def status_snapshot(runtime: Runtime, stats: Mapping[str, Any]) -> dict[str, Any]:
    """The runtime's JSON-able status for the control socket; ``stats``: its last published stats."""
    reference = runtime.reference
    return {
        "state": runtime.lifecycle.state.value,
        "fault": runtime.lifecycle.fault,
        "fault_cycle": runtime.fault_cycle,
        "robot": runtime.config.robot,
        "bundle": str(runtime.config.bundle.path),
        "mode": runtime.config.bundle.mode,
        "reference": reference.name,
        "ramp_cycles": reference.ramp_cycles,
        "cycles": runtime.total_cycles,
        "rate_hz": finite(stats.get("rate_hz")),
        "overruns": runtime.pacer.overruns,
        "compute_median_s": finite(stats.get("compute_median_s")),
        "compute_p99_s": finite(stats.get("compute_p99_s")),
        "supervisor": runtime.supervisor.counters(),
        "bus": counters_dict(runtime.bus.counters),
        "realtime": {"applied": runtime.realtime.applied, "refused": runtime.realtime.refused},
    }
