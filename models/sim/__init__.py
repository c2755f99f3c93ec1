"""Closed-loop simulation: fixed period, zero-order hold, RK4 plant, batched runs."""

from models.sim.closed_loop import ModelPlant, SimConfig, Trajectory, simulate
from models.sim.controllers import MODES, Controller, ControllerStack, FeedbackController, make_controller

__all__ = [
    "MODES",
    "Controller",
    "ControllerStack",
    "FeedbackController",
    "ModelPlant",
    "SimConfig",
    "Trajectory",
    "make_controller",
    "simulate",
]
