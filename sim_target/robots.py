"""The built-in robots' URDFs, found without importing ``models``.

The robot description is data both sides use: ``models/robots/data/robots.yaml`` names each
built-in robot's URDF, next to the files themselves. The target locates that directory through the
import system's finder (``importlib.util.find_spec`` runs no code of the package) and reads the
table, so it never imports ``models`` (tests/unit/test_import_boundaries.py), and the table has one
source: models.robots reads the same file.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import yaml

DEFAULT_ROBOT = "ur5_paper"
_ERD_ROBOTS = Path("cmeel.prefix") / "share" / "example-robot-data" / "robots"


class RobotLookupError(ValueError):
    """A robot name the target cannot turn into a URDF; one line, exit code 2."""

    exit_code = 2


def robot_data_dir() -> Path:
    """``models/robots/data`` of the installed tree (located, not imported)."""
    spec = importlib.util.find_spec("models")
    if spec is None or not spec.submodule_search_locations:
        raise RobotLookupError("robot: the robot descriptions (models/robots/data) are not installed")
    return Path(next(iter(spec.submodule_search_locations))) / "robots" / "data"


def builtin_robots() -> dict[str, dict[str, str]]:
    """The table of robots.yaml: name -> {urdf, end_effector}."""
    table = yaml.safe_load((robot_data_dir() / "robots.yaml").read_text())
    return {str(name): {str(k): str(v) for k, v in entry.items()} for name, entry in table.items()}


def example_robot_data_dir() -> Path:
    """example-robot-data's ``robots/`` tree (a cmeel package: data under ``cmeel.prefix``)."""
    for entry in sys.path:
        candidate = Path(entry) / _ERD_ROBOTS
        if candidate.is_dir():
            return candidate
    raise RobotLookupError("robot data: example-robot-data is not installed (pip install example-robot-data)")


def builtin_urdf_path(name: str = DEFAULT_ROBOT) -> Path:
    """The URDF file of a built-in robot (``ur5_paper``, ``ur5``, ``panda``)."""
    table = builtin_robots()
    if name not in table:
        raise RobotLookupError(f"robot: unknown name '{name}' (known: {', '.join(sorted(table))}, or a .urdf path)")
    kind, relative = table[name]["urdf"].split(":", 1)
    return robot_data_dir() / relative if kind == "local" else example_robot_data_dir() / relative
