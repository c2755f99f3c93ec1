"""What every benchmark's JSON says about the machine it ran on, and how it summarises a timing
(imported by the benchmarks as ``import benchinfo``: ``python benchmarks/<bench>.py`` puts this
folder on sys.path). The machine description is hil_runtime.machine's, shared with the experiment's
results and the fault campaign."""

from __future__ import annotations

import json
import math
import os
import sys
from typing import Any

import numpy as np

from hil_runtime.machine import machine


def spread(values: Any, digits: int = 1) -> dict[str, float]:
    """median, p99 and max of ``values`` (already in the unit the key names), rounded; NaN when empty."""
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        return {"median": math.nan, "p99": math.nan, "max": math.nan}
    return {
        "median": round(float(np.median(values)), digits),
        "p99": round(float(np.percentile(values, 99)), digits),
        "max": round(float(values.max()), digits),
    }


def load_average() -> list[float]:
    """The 1, 5 and 15 minute load averages, rounded: taken before a run, passed to :func:`report`."""
    return [round(x, 2) for x in os.getloadavg()]


def report(benchmark: str, load_before: list[float], fields: dict[str, Any]) -> str:
    """A benchmark's JSON: its name, the command that ran it, ``fields``, the machine and the load
    average before and after the run (one envelope for every benchmark that prints one)."""
    out = {"benchmark": benchmark, "command": "python " + " ".join(sys.argv), **fields}
    out.update(machine=machine(), load_average_before=load_before, load_average_after=load_average())
    return json.dumps(out, indent=1)


__all__ = ["load_average", "machine", "report", "spread"]
