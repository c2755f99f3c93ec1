"""Batch labeling: many independent states solved by the HMPC, spread over an executor's workers.

The work goes through the models' one executor interface (``models.executors``: serial, local
processes, Ray). Each chunk carries the solver's picklable spec (law, robot, config) and its hash;
a worker builds the solver once per spec (``worker_cached``): the pinocchio model lives in C++
and is not shipped between processes, only the description it is built from.

    with make_executor("local", 2) as executor:
        tau, status = solve_batch(law, robot, q, qd, q_d, qd_d, qdd_d, law_state, executor=executor)
"""

from __future__ import annotations

import hashlib
import pickle

import numpy as np

from models.errors import ModelInputError
from models.executors import Executor, SerialExecutor, worker_cached
from models.feedback.base import FeedbackLaw
from models.hmpc.config import HMPCConfig
from models.hmpc.solver import HMPCSolver
from models.robots import RobotModel

DEFAULT_CHUNK_STATES = 256  # rows per vectorized solve: amortizes numpy overhead, bounded memory

SolverSpec = tuple[FeedbackLaw, RobotModel, HMPCConfig]


def _solve_chunk(task: tuple[str, SolverSpec, tuple[np.ndarray, ...]]) -> tuple[np.ndarray, np.ndarray]:
    """Worker: the HMPC on one chunk of states, with this worker's solver for the spec."""
    key, spec, arrays = task
    solver: HMPCSolver = worker_cached(key, lambda: HMPCSolver(*spec))
    # a 7th array: tau_0 per row (the smoothness term and the rate bound apply, as in closed loop)
    previous = arrays[6] if len(arrays) > 6 else None
    q, qd, q_d, qd_d, qdd_d, law_state = arrays[:6]
    result = solver.solve(q, qd, q_d, qd_d, qdd_d, law_state, previous_torque_nm=previous)
    return result.tau_nm, result.status


def solve_batch(
    law: FeedbackLaw,
    robot: RobotModel,
    q: np.ndarray,
    qd: np.ndarray,
    q_d: np.ndarray,
    qd_d: np.ndarray,
    qdd_d: np.ndarray,
    law_state: np.ndarray | None = None,
    config: HMPCConfig | None = None,
    executor: Executor | None = None,
    chunk_states: int = DEFAULT_CHUNK_STATES,
    previous_torque_nm: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """HMPC torques (B, N) and status (B,) for B independent states (cold start, no warm start).

    ``previous_torque_nm`` (B, N): tau_0 per state, the torque applied the period before (the smoothness
    term and the rate bound then apply, as in the closed loop); None: neither (the static optimum).

    Each state is solved exactly as ``HMPCSolver.solve`` solves it alone (rows never interact), so
    the result does not depend on the chunking or the executor.
    """
    config = HMPCConfig() if config is None else config
    q = np.atleast_2d(np.asarray(q, float))
    if law_state is None:
        law_state = law.initial_state(q)
    inputs = (q, qd, q_d, qd_d, qdd_d, law_state) + (() if previous_torque_nm is None else (previous_torque_nm,))
    arrays = [np.atleast_2d(np.asarray(a, float)) for a in inputs]
    batch = q.shape[0]
    if any(a.shape[0] != batch for a in arrays):
        raise ModelInputError(f"solve_batch: every array needs {batch} rows, got {[a.shape[0] for a in arrays]}")
    if chunk_states < 1:
        raise ModelInputError(f"solve_batch chunk_states: must be >= 1, got {chunk_states}")
    bounds = list(range(0, batch, chunk_states)) + [batch]
    chunks = [tuple(a[lo:hi] for a in arrays) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]
    spec: SolverSpec = (law, robot, config)
    key = hashlib.sha256(pickle.dumps(spec)).hexdigest()  # equal specs share a worker's solver
    tasks = [(key, spec, chunk) for chunk in chunks]
    results = list((executor or SerialExecutor()).map(_solve_chunk, tasks))
    return np.concatenate([r[0] for r in results]), np.concatenate([r[1] for r in results])
