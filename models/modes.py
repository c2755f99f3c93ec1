"""The project's controller modes, registered with the simulator's registry (models.sim.controllers).

Import this module (or name a mode through it) to have every built-in mode available:

    from models.modes import MODES, make_controller
    controller = make_controller("hmpc", law, robot, max_iterations=4)

``fb`` is the law alone (models.sim); ``hmpc`` and ``lmpc`` are registered by entry point, so their
packages (numba kernels, onnxruntime) load only when a controller of theirs is made. Another mode
registers itself the same way: ``register_mode("mine", "my_package.module:make_my_controller")``.
"""

from __future__ import annotations

from models.sim.controllers import make_controller, mode_names, register_mode

register_mode("hmpc", "models.hmpc:make_hmpc_controller")
register_mode("lmpc", "models.lmpc:make_lmpc_controller")

MODES = mode_names()

__all__ = ["MODES", "make_controller", "register_mode"]
