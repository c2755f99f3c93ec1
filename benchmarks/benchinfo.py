"""What every benchmark's JSON says about the machine it ran on, and how it summarises a timing
(imported by the benchmarks as ``import benchinfo``: ``python benchmarks/<bench>.py`` puts this
folder on sys.path)."""

from __future__ import annotations

import contextlib
import math
import os
import platform
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np


def machine(*packages: str) -> dict[str, Any]:
    """Platform, CPU model and count, the load average now, and the versions of ``packages``."""
    cpu = ""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    versions: dict[str, str | None] = {}
    for package in packages:
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = None
    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "versions": versions,
    }


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
