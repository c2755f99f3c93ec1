"""Labels (D_sample): the expert's torque on every sampled state.

A labeler is ``labeler(law, robot, rows, executor) -> (tau_star (M, N), status (M,))`` where
``rows`` is a ``RawLaw`` slice carrying q, qd, the reference (q_d, qd_d, qdd_d) and the law's state
before the step: all the HMPC needs to solve the state from scratch (cold start, no warm start).
The default is the project's HMPC (``models.hmpc.solve_batch``); any callable of that signature
plugs in (a distributed labeler, another expert). Status 0 means the MPC converged; any other value
is the HMPC's status code (its torque is then what the HMPC applies in that case, see docs/hmpc.md).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from models.executors import Executor
from models.feedback.base import FeedbackLaw
from models.lmpc.dataset import RawLaw
from models.robots import RobotModel

Labeler = Callable[[FeedbackLaw, RobotModel, RawLaw, Executor | None], tuple[np.ndarray, np.ndarray]]

#: HMPC settings for labeling. A cold solve of a state gets the best iterate when the iteration
#: budget runs out (the closed-loop HMPC, warm-started, rarely runs out; a cold solve often does,
#: and falling back to tau_fb there would teach the emulator the feedback law instead of the MPC).
LABEL_HMPC_OPTIONS: dict[str, Any] = {"on_budget_exhausted": "best_iterate"}


def hmpc_labeler(
    law: FeedbackLaw, robot: RobotModel, rows: RawLaw, executor: Executor | None = None, **hmpc_options: Any
) -> tuple[np.ndarray, np.ndarray]:
    """The project's HMPC on every row (models.hmpc.solve_batch), on ``executor``'s workers."""
    from models.hmpc import HMPCConfig, solve_batch

    config = HMPCConfig.from_options(**{**LABEL_HMPC_OPTIONS, **hmpc_options})
    state = rows.law_state if rows.law_state.shape[1] else None
    return solve_batch(
        law, robot, rows.q, rows.qd, rows.q_d, rows.qd_d, rows.qdd_d, state, config=config, executor=executor
    )
