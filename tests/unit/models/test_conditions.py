from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from models.conditions import load_conditions, random_conditions
from models.errors import ModelInputError
from models.robots import load_robot

ROBOT = load_robot("ur5_paper")


def test_paper_conditions_match_eq27() -> None:
    conditions = load_conditions(robot=ROBOT)
    assert [c.name for c in conditions] == ["C1", "C2", "C3", "C4", "C5"]
    c1, c4 = conditions[0], conditions[3]
    assert c1.amplitude_rad == pytest.approx(
        (-math.pi / 4, math.pi / 6, -math.pi / 6, -math.pi / 4, math.pi / 2, math.pi / 2)
    )
    assert conditions[1].amplitude_rad == pytest.approx(tuple(-a for a in c1.amplitude_rad))
    t = np.array([0.0, 1.3, 4.9])
    q, qd, qdd = c4.reference(t)
    expected = 0.5 * np.array(c4.amplitude_rad) * (1 + np.sin(2 * math.pi * 0.05 * (t[:, None] - 2.5)))
    assert q == pytest.approx(expected)
    assert c1.reference(0.0)[0] == pytest.approx(np.zeros(6))  # f = 0.1 starts at q = 0
    assert c4.reference(0.0)[0] / np.array(c4.amplitude_rad) == pytest.approx(np.full(6, 0.1464466), rel=1e-6)
    # derivatives by central differences
    h = 1e-6
    assert qd == pytest.approx((c4.reference(t + h)[0] - c4.reference(t - h)[0]) / (2 * h), abs=1e-7)
    assert qdd == pytest.approx((c4.reference(t + h)[1] - c4.reference(t - h)[1]) / (2 * h), abs=1e-6)
    assert c1.disturbance is not None and c1.disturbance.torque_nm == (1, 1, 5, 5, 10, 10)


def test_random_conditions_are_seeded_and_inside_limits() -> None:
    a, b = random_conditions(ROBOT, 20, seed=5), random_conditions(ROBOT, 20, seed=5)
    assert [c.amplitude_rad for c in a] == [c.amplitude_rad for c in b]
    assert [c.amplitude_rad for c in a] != [c.amplitude_rad for c in random_conditions(ROBOT, 20, seed=6)]
    for c in a:
        c.check_limits(ROBOT)


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("conditions:\n  - name: A\n    frequency_hz: 0.1\n", "conditions[0].amplitude_rad: missing"),
        (
            "conditions:\n  - name: A\n    amplitude_rad: [1, 2, x, 0, 0, 0]\n",
            "conditions[0].amplitude_rad[2]: not a number",
        ),
        ("conditions:\n  - name: A\n    amplitude_rad: [.nan, 0, 0, 0, 0, 0]\n", "amplitude_rad[0]: not finite"),
        (
            "conditions:\n  - name: A\n    amplitude_rad: [4, 0, 0, 0, 0, 0]\n",
            "reference position reaches 4.000 on joint 1",
        ),
        ("conditions:\n  - name: A\n    amplitude_rad: [0, 0, 0]\n", "has 3 joints"),
        ("conditions: [\n", "not valid YAML"),
        (
            "conditions:\n  - name: A\n    amplitude_rad: [0, 0, 0, 0, 0, 0]\n    disturbance: {time_s: abc}\n",
            "conditions[0].disturbance.time_s: not a number",
        ),
        (
            "conditions:\n  - name: A\n    amplitude_rad: [0, 0, 0, 0, 0, 0]\n    colour: red\n",
            "unknown field 'colour'",
        ),
    ],
)
def test_bad_condition_files_give_one_line_errors(tmp_path: Path, body: str, message: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(body)
    with pytest.raises(ModelInputError) as info:
        load_conditions(path, robot=ROBOT)
    assert message in str(info.value) and "bad.yaml" in str(info.value)
    assert "\n" not in str(info.value)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ModelInputError, match="file not found"):
        load_conditions(tmp_path / "nope.yaml")
