"""A law whose every training rollout left the limits: ``hil pipeline`` says so in one line (it crashed
with a numpy traceback in the relabeling, handed zero states, on the real UR5: docs/any_arm.md)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

pytest.importorskip("torch")

from models.errors import ModelInputError
from models.lmpc.paper_range import paper_range_conditions
from models.lmpc.structured import StructuredConfig
from models.lmpc.structured import data as structured_data
from models.robots import load_robot


def test_a_law_with_no_rollout_inside_the_limits_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_rows(robot: Any, controllers: list[Any], *args: Any, **kwargs: Any) -> list[dict[str, np.ndarray]]:
        n = robot.n_joints
        return [{k: np.zeros((0, n)) for k in ("q", "qd", "q_d", "qd_d", "qdd_d", "tau_fb")} for _ in controllers]

    monkeypatch.setattr(structured_data, "_logged_rollouts", no_rows)
    config = StructuredConfig(robot="ur5_paper", laws=("pd",))
    conditions = paper_range_conditions(load_robot("ur5_paper"), 2, 1, prefix="T")
    with pytest.raises(ModelInputError, match=r"^structured LMPC data on ur5_paper: every HMPC rollout of pd left"):
        structured_data.collect(config, conditions)
