"""What a results file says about the machine that produced it (figures are only comparable with it).

One description for the benchmarks (``benchmarks/benchinfo.py``), ``hil experiment``'s results.json
and the fault campaign: platform, CPU model and count, the load average when it was taken, and the
versions of the packages the figures depend on.
"""

from __future__ import annotations

import contextlib
import os
import platform
from importlib import metadata
from pathlib import Path
from typing import Any


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), else what ``platform`` knows (often only the architecture)."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def machine(*packages: str) -> dict[str, Any]:
    """Platform, CPU model and count, the load average now, and the versions of ``packages``
    (distribution names, e.g. "numpy", "pin", "python-can"; None when not installed)."""
    versions: dict[str, str | None] = {}
    for package in packages:
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = None
    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "versions": versions,
    }


__all__ = ["cpu_model", "machine"]
