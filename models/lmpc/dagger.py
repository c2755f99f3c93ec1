"""One DAgger-style round (beyond the paper): HMPC labels on the states the LMPC closed loop visits.

    states = lmpc_visited_states(bundle_dir, robot, laws, conditions)       # per law: RawLaw
    (label them with models.lmpc.labels.hmpc_labeler, add to the training set, retrain, export)

Only states inside the joint position and velocity limits are kept: a run that has diverged visits
states no controller should be trained for.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.conditions import Condition
from models.feedback import make_law
from models.lmpc.controller import make_lmpc_controller
from models.lmpc.dataset import RawLaw
from models.lmpc.expert_rollouts import StateLogger
from models.robots import RobotModel
from models.sim import ControllerStack, SimConfig, simulate


def lmpc_visited_states(
    bundle_dir: Path,
    robot: RobotModel,
    laws: tuple[str, ...],
    conditions: list[Condition],
    sim: SimConfig | None = None,
    stride: int = 5,
    gain_set: str | None = None,
) -> dict[str, RawLaw]:
    """Run every law's LMPC bundle on ``conditions``; the logged states inside the limits, per law."""
    sim = SimConfig() if sim is None else sim
    steps = int(round(conditions[0].duration_s / sim.period_s))
    kwargs = {} if gain_set is None else {"gain_set": gain_set}
    controllers = [
        make_lmpc_controller(make_law(law, robot, sim.period_s, **kwargs), robot, bundle_dir=bundle_dir) for law in laws
    ]
    loggers = [
        StateLogger(
            c,
            len(conditions),
            steps,
            stride,
            c.bundle.n_joints,
            c.bundle.state_size,
            log_applied=False,
        )
        for c in controllers
    ]
    with np.errstate(all="ignore"):
        simulate(
            robot, ControllerStack(loggers, [len(conditions)] * len(laws)), [c for _ in laws for c in conditions], sim
        )
    out = {}
    for law, logger in zip(laws, loggers, strict=True):
        rows = logger.log["t_s"].size
        flat = {k: v.reshape(len(conditions) * rows, -1) for k, v in logger.log.items() if k != "t_s"}
        t_s = np.tile(logger.log["t_s"], len(conditions))
        run = np.repeat(np.arange(len(conditions)), rows)
        inside = (
            np.all(np.abs(flat["q"]) <= robot.position_limit_rad, 1)
            & np.all(np.abs(flat["qd"]) <= robot.velocity_limit_rad_s, 1)
            & np.all(np.isfinite(flat["law_state"]), 1)
            & np.all(np.isfinite(flat["tau_fb"]), 1)
        )
        out[law] = RawLaw(
            t_s[inside],
            run[inside],
            *(flat[k][inside] for k in ("q", "qd", "q_d", "qd_d", "qdd_d", "law_state", "tau_fb")),
        )
    return out
