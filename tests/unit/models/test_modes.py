"""The controller-mode registry: modes fill it in; the simulator imports no MPC package."""

from __future__ import annotations

import subprocess
import sys
from typing import Any

import numpy as np
import pytest

from models.errors import ModelInputError
from models.feedback import make_law
from models.modes import MODES, make_controller
from models.robots import load_robot
from models.sim import FeedbackController, controllers, register_mode

ROBOT = load_robot("ur5_paper")


def test_builtin_modes_are_registered_and_unknown_ones_named() -> None:
    assert MODES == ("fb", "hmpc", "lmpc")
    with pytest.raises(ModelInputError, match="unknown 'mpc' \\(known: fb, hmpc, lmpc"):
        make_controller("mpc", make_law("pd", ROBOT), ROBOT)


def test_a_registered_factory_and_a_lazy_entry_point_are_made(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(controllers, "_MODES", dict(controllers._MODES))
    law = make_law("pd", ROBOT)
    made: list[tuple] = []

    def mine(law: Any, robot: Any, **options: Any) -> FeedbackController:
        made.append((law, robot, options))
        return FeedbackController(law)

    register_mode("mine", mine)
    assert isinstance(make_controller("mine", law, ROBOT, gain=2), FeedbackController)
    assert made == [(law, ROBOT, {"gain": 2})]
    register_mode("lazy", "models.sim.controllers:_feedback_only")
    controller = make_controller("lazy", law, ROBOT)
    assert isinstance(controller, FeedbackController) and controller.law is law
    assert controllers._MODES["lazy"] is controllers._feedback_only  # resolved once, then kept
    tau = controller(0.0, *(np.zeros((1, 6)) for _ in range(5)))
    assert tau.shape == (1, 6)


def test_registration_refuses_a_malformed_entry_point_and_a_second_factory(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(controllers, "_MODES", dict(controllers._MODES))
    with pytest.raises(ValueError, match="'module:attribute'"):
        register_mode("bad", "models.hmpc.make_hmpc_controller")
    register_mode("hmpc", "models.hmpc:make_hmpc_controller")  # the same again: harmless
    with pytest.raises(ValueError, match="already registered"):
        register_mode("hmpc", "models.lmpc:make_lmpc_controller")


def test_the_simulator_imports_no_mpc_package() -> None:
    code = (
        "import sys, models.sim, models.modes\n"
        "loaded = [m for m in ('models.hmpc', 'models.lmpc') if m in sys.modules]\n"
        "assert not loaded, loaded\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
