"""The architecture's dependency rules (docs/architecture.md, "Dependency direction"), checked on
every module of the three deployable packages, two ways:

- imported, each package in a fresh interpreter, module by module: nothing forbidden may end up in
  ``sys.modules`` (catches what a module pulls in transitively, as a user's process would see it);
- read, every ``import`` statement of every file, also those inside functions (a lazy import is
  still a dependency; it would only fail later, on the machine next to the arm).

``hil_runtime`` and ``drivers`` never import models, sim_target, torch, pinocchio or pybullet;
``sim_target`` imports drivers and pybullet, never hil_runtime or models.
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

# Known exceptions, each with its reason; an import not listed here fails the test.
# sim_target/faults is the `hil faults` campaign: it runs the runtime daemon against the target and
# judges it, so it needs both sides (lazy imports, inside the functions that start the runtime).
# It belongs beside them, not inside the target; until it moves, its imports are allowed here.
ALLOWED: dict[str, frozenset[str]] = {
    "sim_target.faults": frozenset({"hil_runtime"}),
}

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


def _allowed(module: str) -> frozenset[str]:
    return frozenset().union(*(v for k, v in ALLOWED.items() if module == k or module.startswith(k + ".")))


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
    pulled = {m: sorted(set(v) - _allowed(m)) for m, v in report["pulled"].items()}
    assert {m: v for m, v in pulled.items() if v} == {}, f"{package}: modules that pull in a forbidden package"


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_no_import_statement_crosses_the_architecture(package: str) -> None:
    files = sorted(p for p in (ROOT / package).rglob("*.py") if "__pycache__" not in p.parts)
    assert files
    crossings = {}
    for path in files:
        module = _module_name(path)
        bad = (_imported_top_levels(path) & FORBIDDEN[package]) - _allowed(module)
        if bad:
            crossings[module] = sorted(bad)
    assert crossings == {}, f"{package}: import statements (also inside functions) that cross the architecture"


def test_the_guard_sees_a_lazy_import(tmp_path: Path) -> None:
    """The static check reads imports inside functions, relative ones excluded."""
    source = tmp_path / "m.py"
    source.write_text("def f():\n    import torch.nn\n    from models.robots import urdf_path\n    from . import x\n")
    assert _imported_top_levels(source) == {"torch", "models"}
