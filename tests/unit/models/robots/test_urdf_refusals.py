"""URDF inputs the robot loader must refuse with one line naming file and element (issue 9, item 4)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from models.errors import ModelInputError
from models.robots import load_robot
from models.robots.description import urdf_path

UR5_PAPER = urdf_path("ur5_paper").read_text()


def _variant(tmp_path: Path, pattern: str, replacement: str) -> Path:
    text, count = re.subn(pattern, replacement, UR5_PAPER, count=1, flags=re.DOTALL)
    assert count == 1, pattern
    path = tmp_path / "variant.urdf"
    path.write_text(text)
    return path


CASES = [
    (r"<limit [^>]*/>", "", "joint 'shoulder_pan_joint' <limit>: missing"),
    (
        r'(<joint name="elbow_joint" type=)"revolute"',
        r'\1"prismatic"',
        "joint 'elbow_joint' type 'prismatic' on the arm's chain",
    ),
    (r'(<joint name="wrist_3_joint" type=)"revolute"', r'\1"prismatic"', "joint 'wrist_3_joint' type 'prismatic'"),
    (r'ixx="', 'ixx="-', "<inertia> ixx: negative"),
    (r'ixy="[^"]*"', 'ixy="5"', "<inertia>: not positive semi-definite"),
    (r'<mass value="', '<mass value="-', "<mass> value: negative"),
    (r'(<limit [^>]*lower=")[^"]*(")', r"\g<1>4\2", "lower 4 above upper"),
    (r'(<limit [^>]*velocity=")[^"]*(")', r"\g<1>nan\2", "expected 1 finite numbers"),
]


@pytest.mark.parametrize(("pattern", "replacement", "message"), CASES)
def test_refused_with_one_line(tmp_path: Path, pattern: str, replacement: str, message: str) -> None:
    path = _variant(tmp_path, pattern, replacement)
    with pytest.raises(ModelInputError) as info:
        load_robot(path)
    assert message in str(info.value) and "variant.urdf" in str(info.value) and "\n" not in str(info.value)


def test_the_builtin_robots_still_load() -> None:
    assert [load_robot(n).n_joints for n in ("ur5_paper", "ur5", "panda")] == [6, 6, 7]  # panda's fingers: locked
