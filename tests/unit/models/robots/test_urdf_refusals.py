"""URDF inputs the robot loader must refuse with one line naming file and element (issue 9, item 4)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
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
    # issue 25 item 4
    (
        r'<link name="base_link"/>',
        '<link name="world"/><joint name="free" type="floating"><parent link="world"/><child link="base_link"/>'
        '</joint><link name="base_link"/>',
        "joint 'free' type 'floating': a floating base is not supported",
    ),
    (
        r'<link name="base_link"/>',
        '<link name="base_link"/><joint name="strut" type="fixed"><parent link="base_link"/>'
        '<child link="forearm_link"/></joint>',
        "link 'forearm_link' is the child of joints 'strut' and 'elbow_joint': a closed chain",
    ),
    (
        r'(<joint name="elbow_joint" type=)"revolute"(.*?)<limit [^>]*/>',
        r'\1"continuous"\2',
        "joint 'elbow_joint' <limit>: missing (a continuous joint needs effort and velocity)",
    ),
    (
        r'(<joint name="elbow_joint" type="revolute">)',
        r'\1<mimic joint="shoulder_lift_joint"/>',
        "joint 'elbow_joint' <mimic>: a mimic joint on the arm's chain is not supported",
    ),
    (
        r'<mass value="0.4"/>\s*<inertia [^>]*/>',
        '<mass value="0"/><inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/>',
        "joint 'wrist_3_joint' moves no inertia",
    ),
    (r'effort="102" ', "", "joint 'shoulder_pan_joint' <limit> effort: missing"),
    (
        r'(<limit lower="-3.14159265359" upper="3.14159265359" effort="102") velocity="[^"]*"',
        r"\1",
        "<limit> velocity: missing",
    ),
]


@pytest.mark.parametrize(("pattern", "replacement", "message"), CASES)
def test_refused_with_one_line(tmp_path: Path, pattern: str, replacement: str, message: str) -> None:
    path = _variant(tmp_path, pattern, replacement)
    with pytest.raises(ModelInputError) as info:
        load_robot(path)
    assert message in str(info.value) and "variant.urdf" in str(info.value) and "\n" not in str(info.value)


def test_a_continuous_joint_is_treated_as_unbounded_in_position(tmp_path: Path) -> None:
    robot = load_robot(_variant(tmp_path, r'(<joint name="elbow_joint" type=)"revolute"', r'\1"continuous"'))
    assert robot.position_lower_rad[2] == -np.inf and robot.position_upper_rad[2] == np.inf
    assert robot.torque_limit_nm[2] == 66.0 and robot.position_upper_rad[1] == pytest.approx(2.51327412287)


def test_the_builtin_robots_still_load() -> None:
    assert [load_robot(n).n_joints for n in ("ur5_paper", "ur5", "panda")] == [6, 6, 7]  # panda's fingers: locked
