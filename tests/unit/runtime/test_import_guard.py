"""The runtime side never imports the science side: every module of ``hil_runtime`` and
``drivers`` imports without pulling in models, sim_target, torch, pinocchio or pybullet
(ARCHITECTURE.md, dependency direction). Run in a fresh interpreter so nothing is preloaded."""

from __future__ import annotations

import json
import subprocess
import sys

FORBIDDEN = ("models", "sim_target", "torch", "pinocchio", "pybullet", "scipy", "numba")

CODE = r"""
import importlib, json, pkgutil, sys
import hil_runtime, drivers
names = []
for package in (hil_runtime, drivers):
    names.append(package.__name__)
    for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
        names.append(info.name)
failed = {}
for name in names:
    try:
        importlib.import_module(name)
    except Exception as exc:  # reported, not hidden
        failed[name] = repr(exc)
forbidden = FORBIDDEN
loaded = sorted({m.split(".")[0] for m in sys.modules} & set(forbidden))
print(json.dumps({"modules": names, "failed": failed, "loaded": loaded}))
"""


def test_no_runtime_or_driver_module_imports_the_science_side() -> None:
    code = CODE.replace("forbidden = FORBIDDEN", f"forbidden = {FORBIDDEN!r}")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert {"hil_runtime.runtime", "hil_runtime.daemon", "hil_runtime.supervisor", "drivers.drive_bus"} <= set(
        report["modules"])
    assert report["failed"] == {}, report["failed"]
    assert report["loaded"] == [], f"imported by the runtime side: {report['loaded']}"
