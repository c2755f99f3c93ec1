"""Closed-loop simulation: fixed period, zero-order hold, RK4 plant, batched runs.

The controller modes beyond ``fb`` are registered by ``models.modes``.
"""

from models.sim.closed_loop import ModelPlant, SimConfig, Trajectory, batch_key, simulate
from models.sim.controllers import (
    Controller,
    ControllerStack,
    FeedbackController,
    make_controller,
    mode_names,
    register_mode,
)

__all__ = [
    "batch_key",
    "Controller",
    "ControllerStack",
    "FeedbackController",
    "ModelPlant",
    "SimConfig",
    "Trajectory",
    "make_controller",
    "mode_names",
    "register_mode",
    "simulate",
]
