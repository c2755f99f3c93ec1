"""The architecture's dependency rules (docs/architecture.md, "Dependency direction"), checked on
every module of the three deployable packages, two ways:

- imported, each package in a fresh interpreter, module by module: nothing forbidden may end up in
  ``sys.modules`` (catches what a module pulls in transitively, as a user's process would see it);
- read, every ``import`` statement of every file, also those inside functions (a lazy import is
  still a dependency; it would only fail later, on the machine next to the arm).

``hil_runtime`` and ``drivers`` never import models, sim_target, torch, pinocchio or pybullet;
``sim_target`` imports drivers and pybullet, never hil_runtime or models. In ``models``, only the
lab (``models/lab``, the composition root of the demo, the HIL experiment and the fault campaign)
imports drivers and the runtime's internals; the rest uses the runtime's public APIs listed in
``MODELS_RUNTIME_API`` (read statically, every import statement of every file).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

# package -> top-level modules it must never import (the science stack stays behind extras)
FORBIDDEN: dict[str, frozenset[str]] = {
    "hil_runtime": frozenset({"models", "sim_target", "torch", "pinocchio", "pybullet", "scipy", "numba"}),
    "drivers": frozenset({"hil_runtime", "models", "sim_target", "torch", "pinocchio", "pybullet", "scipy", "numba"}),
    "sim_target": frozenset({"hil_runtime", "models", "torch", "pinocchio"}),
}

# What models outside models/lab may import of the runtime, each with its reason; anything else of
# hil_runtime (the Runtime, its factory, the daemon, the loop, the supervisor, the config) and all of
# drivers belong to the lab.
MODELS_RUNTIME_API: dict[str, str] = {
    "hil_runtime.bundle": "the bundle API: experiments score exactly what the runtime runs",
    "hil_runtime.bundle_schema": "the bundle API: the manifest's schema, shared by writer and loader",
    "hil_runtime.bundle_security": "the bundle API: the manifest's seal and signatures",
    "hil_runtime.trust_region": "the bundle API: the emulator's trust features, exported into the bundle",
    "hil_runtime.rate_limit": "the bundle API: the policy's torque-rate limit, applied alike by the simulator",
    "hil_runtime.velocity_filter": "the bundle API: the policy's velocity input filter, applied alike by the simulator",
    "hil_runtime.conditions": "the operating conditions, evaluated by the runtime and the simulator alike",
    "hil_runtime.outputs": "atomic output files and directories (results, tables, plots)",
    "hil_runtime.machine": "the machine description stamped on results",
    "hil_runtime.telemetry.subscriber": "the public telemetry decoder (contract 3): the demo subscribes",
    "hil_runtime.telemetry.codec": "the public telemetry decoder's payload layouts",
    "hil_runtime.telemetry.cli": "the `hil watch` view the demo shows",
    "hil_runtime.telemetry.config": "a subscriber's Zenoh session config (loopback, no scouting)",
    "hil_runtime.control": "the control socket's client (status of a daemon the demo started)",
}
MODELS_LAB = "models.lab"

CODE = r"""
import importlib, json, pkgutil, sys
package = importlib.import_module(PACKAGE)
forbidden = set(FORBIDDEN)
names = [package.__name__] + [i.name for i in pkgutil.walk_packages(package.__path__, package.__name__ + ".")]
failed, pulled = {}, {}
for name in names:
    before = {m.split(".")[0] for m in sys.modules}
    try:
        importlib.import_module(name)
    except Exception as exc:  # reported, not hidden
        failed[name] = repr(exc)
    new = sorted(({m.split(".")[0] for m in sys.modules} - before) & forbidden)
    if new:
        pulled[name] = new
print(json.dumps({"modules": names, "failed": failed, "pulled": pulled}))
"""


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported_top_levels(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_every_module_imports_without_the_forbidden_side(package: str) -> None:
    code = CODE.replace("PACKAGE", repr(package)).replace("FORBIDDEN", repr(sorted(FORBIDDEN[package])))
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180, check=False)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    files = [p for p in (ROOT / package).rglob("*.py") if "__pycache__" not in p.parts]
    assert len(report["modules"]) == len(files), "every file is a module the walk reached"
    assert report["failed"] == {}, report["failed"]
    assert report["pulled"] == {}, f"{package}: modules that pull in a forbidden package"


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_no_import_statement_crosses_the_architecture(package: str) -> None:
    files = sorted(p for p in (ROOT / package).rglob("*.py") if "__pycache__" not in p.parts)
    assert files
    crossings = {}
    for path in files:
        module = _module_name(path)
        bad = _imported_top_levels(path) & FORBIDDEN[package]
        if bad:
            crossings[module] = sorted(bad)
    assert crossings == {}, f"{package}: import statements (also inside functions) that cross the architecture"


def test_the_guard_sees_a_lazy_import(tmp_path: Path) -> None:
    """The static check reads imports inside functions, relative ones excluded."""
    source = tmp_path / "m.py"
    source.write_text("def f():\n    import torch.nn\n    from models.robots import urdf_path\n    from . import x\n")
    assert _imported_top_levels(source) == {"torch", "models"}


def _imported_modules(path: Path) -> set[str]:
    """Every absolute module an import statement names (``from a import b``: ``a.b`` when ``a`` is a
    package the rule looks into, so ``from hil_runtime import conditions`` is hil_runtime.conditions)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module in ("hil_runtime", "hil_runtime.telemetry"):
                names.update(f"{node.module}.{alias.name}" for alias in node.names)
            else:
                names.add(node.module)
    return names


def _lab_only(modules: set[str]) -> list[str]:
    """The imports of ``modules`` that only the lab may make."""
    bad = []
    for name in sorted(modules):
        top = name.split(".")[0]
        if top == "drivers":
            bad.append(name)
        elif top == "hil_runtime" and not any(name == a or name.startswith(a + ".") for a in MODELS_RUNTIME_API):
            bad.append(name)
    return bad


def test_only_the_lab_imports_the_runtime_beyond_its_public_apis() -> None:
    files = sorted(p for p in (ROOT / "models").rglob("*.py") if "__pycache__" not in p.parts)
    outside = [p for p in files if not _module_name(p).startswith(MODELS_LAB)]
    assert outside and len(outside) < len(files), "the lab and the rest of models are both there"
    crossings = {_module_name(p): bad for p in outside if (bad := _lab_only(_imported_modules(p)))}
    assert crossings == {}, "models outside models/lab importing drivers or the runtime's internals"


def test_the_models_guard_tells_the_bundle_api_from_the_runtime(tmp_path: Path) -> None:
    source = tmp_path / "m.py"
    source.write_text(
        "from hil_runtime import conditions\nfrom hil_runtime.bundle import PolicyBundle\n"
        "def f():\n    from hil_runtime.factory import build_runtime\n    import drivers.drive_bus\n"
        "    from hil_runtime import runtime\n"
    )
    assert _lab_only(_imported_modules(source)) == ["drivers.drive_bus", "hil_runtime.factory", "hil_runtime.runtime"]
