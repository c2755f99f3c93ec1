"""Checks of command-line values shared by the ``hil`` science commands: each refuses a bad value
with one line naming the option (``ModelInputError``: exit code 2, no traceback)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Annotated

import typer

from models.errors import ModelInputError

# The built-in robots (models.robots.robot_names(); tests/unit/models/test_readme_snippets.py keeps them equal).
ROBOTS_HELP = "ur5_paper, ur5, panda"

#: ``--robot`` of the commands that run the laws with the shipped gain sets.
RobotOption = Annotated[
    str,
    typer.Option(
        help=f"Robot: {ROBOTS_HELP}, or a URDF path. The gain sets are ur5_paper's: on another robot the laws need "
        "their own gains (models.feedback.make_law), so this command refuses it."
    ),
]


def positive(value: float, option: str, integer: bool = False) -> None:
    """Refuse zero, negative or non-finite values of a numeric option."""
    if not (math.isfinite(value) and value > 0):
        kind = "a positive integer" if integer else "a positive finite number"
        raise ModelInputError(f"{option}: must be {kind}, got {value!r}")


def one_of(value: str, known: Iterable[str], option: str) -> str:
    """``value`` if it is one of ``known``."""
    known = tuple(known)
    if value not in known:
        raise ModelInputError(f"{option}: unknown '{value}' (known: {', '.join(known)})")
    return value


def split_names(text: str, known: tuple[str, ...], what: str) -> tuple[str, ...]:
    """A comma-separated list of names (case-insensitive), each one of ``known``; ``what``: the option
    without its dashes."""
    items = tuple(x.strip().lower() for x in text.split(",") if x.strip())
    if not items:
        raise ModelInputError(f"--{what}: empty")
    for item in items:
        one_of(item, known, f"--{what}")
    return items
