"""What every benchmark's JSON says about the machine it ran on, and how it summarises a timing
(imported by the benchmarks as ``import benchinfo``: ``python benchmarks/<bench>.py`` puts this
folder on sys.path). The machine description is hil_runtime.machine's, shared with the experiment's
results and the fault campaign."""

from __future__ import annotations

import math
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


__all__ = ["machine", "spread"]
