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

#: ``--robot`` of the commands that run the laws.
RobotOption = Annotated[
    str,
    typer.Option(
        help=f"Robot: {ROBOTS_HELP}, or a URDF path. ur5_paper runs the paper's gains and five conditions; any "
        "other arm the gains designed from its URDF and its own default conditions (docs/any_arm.md)."
    ),
]
#: ``--gains`` of the commands that run the laws: None picks the robot's default (:func:`gain_set_for`).
GainsOption = Annotated[
    str | None,
    typer.Option(
        help="Gain set: 'stabilized' (ur5_paper's default), 'paper' (ur5_paper), 'designed' (from the URDF: "
        "every other robot's default) (docs/feedback_laws.md)."
    ),
]
#: ``--realism`` of the commands that run the HIL plant (sim_target.realism's profiles).
RealismOption = Annotated[
    str,
    typer.Option(
        help="Realism profile: ideal, realistic, harsh, or a profile YAML (docs/realism.md).",
        metavar="PROFILE|FILE",
    ),
]
#: The gain set of a robot other than ur5_paper: designed from its URDF (models/feedback/design.py).
DESIGNED_GAIN_SET = "designed"


def gain_set_for(robot_name: str, gains: str | None) -> str:
    """``--gains``, else the robot's default: ur5_paper's shipped set, the designed one for any other arm."""
    from models.feedback import DEFAULT_GAIN_SET, GAIN_SET_ROBOT, GAIN_SETS

    if gains is None:
        gains = DEFAULT_GAIN_SET if robot_name == GAIN_SET_ROBOT else DESIGNED_GAIN_SET
    return one_of(gains, GAIN_SETS, "--gains")


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
