"""The README's robots snippet runs as printed (issue 9: it raised NameError: q)."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parents[3] / "README.md"


def test_the_robots_and_dynamics_snippet_runs() -> None:
    block = re.search(r"## Robots and dynamics\n\n```python\n(.*?)```", README.read_text(), re.S)
    assert block is not None, "README: the 'Robots and dynamics' snippet moved"
    namespace: dict = {}
    exec(compile(block.group(1), "README.md", "exec"), namespace)  # noqa: S102 - our own documentation
    assert namespace["tau"].shape == (namespace["robot"].n_joints,)


def test_the_robot_help_lists_the_builtin_robots() -> None:
    from models.cli import ROBOTS_HELP
    from models.robots import robot_names

    assert sorted(ROBOTS_HELP.split(", ")) == robot_names()
