"""Expert rollouts: states the HMPC's own closed loop visits, labeled with the torque it applied.

Beyond the paper. D_input holds feedback-only runs, whose tracking errors are large; the HMPC keeps
the error near zero, so the LMPC's closed loop lives where D_input has almost no samples and the
emulator's errors compound (docs/lmpc.md). These runs add the expert's own state distribution
(the first step of DAgger; the labels are the warm-started HMPC torques actually applied).

    arrays = hmpc_rollouts(spec, conditions, executor)   # per law: RawLaw fields + tau_star
"""

from __future__ import annotations

from typing import Any

import numpy as np

from models.conditions import Condition
from models.executors import Executor, SerialExecutor
from models.feedback import make_law
from models.robots import load_robot
from models.sim import ControllerStack, SimConfig, simulate


def _expert_logger(inner: Any, batch: int, steps: int, stride: int) -> StateLogger:
    return StateLogger(
        inner,
        batch,
        steps,
        stride,
        inner.law.n_joints,
        inner.law.state_size,
        log_applied=True,
    )


class StateLogger:
    """Wraps a controller; logs every ``stride``-th period with the law state before the call.

    Every controller (FB, HMPC, LMPC) keeps its law state in ``state`` (B, S); with ``log_applied`` the
    torque the controller applied is logged too (as ``tau_star``: the expert's label).
    """

    def __init__(
        self,
        inner: Any,
        batch: int,
        steps: int,
        stride: int,
        n_joints: int,
        state_size: int,
        log_applied: bool,
        log_previous: bool = False,
    ) -> None:
        self.inner, self.stride, self.log_applied = inner, stride, log_applied
        # log_previous: also tau_prev, the torque this controller applied the period before (its tau_0; on
        # the first period the torque it applies then: no change, as the HMPC's first cycle has no tau_0)
        self.log_previous = log_previous
        self._previous: np.ndarray | None = None
        self.name = inner.name + "-log"
        self.cycle_times_s: list[float] = []
        self.last_tau_fb: np.ndarray | None = None
        rows = (steps + stride - 1) // stride
        keys = ("q", "qd", "q_d", "qd_d", "qdd_d", "tau_fb") + (("tau_star",) if log_applied else ())
        keys += ("tau_prev",) if log_previous else ()
        self.log = {k: np.empty((batch, rows, n_joints)) for k in keys}
        self.log["law_state"] = np.empty((batch, rows, state_size))
        self.log["t_s"] = np.empty(rows)

    def reset(self, q0: np.ndarray) -> None:
        self.inner.reset(q0)
        self.k = 0
        self._previous = None

    def __call__(
        self, t_s: float, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray
    ) -> np.ndarray:
        before = np.array(self.inner.state)  # the law state before the call (a copy)
        tau = self.inner(t_s, q, qd, q_d, qd_d, qdd_d)
        self.last_tau_fb = self.inner.last_tau_fb
        if self.k % self.stride == 0:
            row, log = self.k // self.stride, self.log
            log["t_s"][row] = t_s
            values = [
                ("q", q),
                ("qd", qd),
                ("q_d", q_d),
                ("qd_d", qd_d),
                ("qdd_d", qdd_d),
                ("tau_fb", self.last_tau_fb),
                ("law_state", before),
            ]
            if self.log_applied:
                values.append(("tau_star", tau))
            if self.log_previous:
                values.append(("tau_prev", tau if self._previous is None else self._previous))
            for key, value in values:
                log[key][:, row] = value
        if self.log_previous:
            self._previous = np.array(tau, float)
        self.k += 1
        return tau


def _rollout_chunk(task: tuple) -> dict[str, Any]:
    from models.hmpc import make_hmpc_controller

    robot_name, laws, gain_set, conditions, sim, stride = task
    robot = load_robot(robot_name)
    steps = int(round(conditions[0].duration_s / sim.period_s))
    loggers = [
        _expert_logger(
            make_hmpc_controller(make_law(law, robot, sim.period_s, gain_set), robot), len(conditions), steps, stride
        )
        for law in laws
    ]
    simulate(robot, ControllerStack(loggers, [len(conditions)] * len(laws)), [c for _ in laws for c in conditions], sim)
    out = {}
    for law, logger in zip(laws, loggers, strict=True):
        rows = logger.log["t_s"].size
        out[law] = {
            "t_s": np.tile(logger.log["t_s"], len(conditions)),
            **{k: v.reshape(len(conditions) * rows, -1) for k, v in logger.log.items() if k != "t_s"},
        }
    return out


def hmpc_rollouts(
    robot_name: str,
    laws: tuple[str, ...],
    gain_set: str,
    conditions: list[Condition],
    sim: SimConfig,
    stride: int = 5,
    chunks: int = 2,
    executor: Executor | None = None,
) -> dict[str, dict[str, np.ndarray]]:
    bounds = np.linspace(0, len(conditions), min(chunks, len(conditions)) + 1).astype(int)
    tasks = [
        (robot_name, laws, gain_set, conditions[a:b], sim, stride) for a, b in zip(bounds[:-1], bounds[1:], strict=True)
    ]
    parts = list((executor or SerialExecutor()).map(_rollout_chunk, tasks))
    return {law: {k: np.concatenate([p[law][k] for p in parts]) for k in parts[0][law]} for law in laws}
