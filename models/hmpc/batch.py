"""Batch labeling: many independent states solved by the HMPC, spread over worker processes.

The science code sees one small interface, ``BatchExecutor.map(fn, chunks)``; a serial and a
process-pool executor are here, and a distributed engine (e.g. Ray) can implement the same method
later. The solver is rebuilt once per worker from its picklable spec (law, robot, config): the
pinocchio model lives in C++ and is not shipped between processes.

    tau = solve_batch(law, robot, q, qd, q_d, qd_d, qdd_d, law_state, executor=ProcessPoolBatchExecutor(2))
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Protocol

import numpy as np

from models.errors import ModelInputError
from models.feedback.base import FeedbackLaw
from models.hmpc.config import HMPCConfig
from models.hmpc.solver import HMPCResult, HMPCSolver
from models.robots import RobotModel

DEFAULT_CHUNK_STATES = 256  # rows per vectorized solve: amortizes numpy overhead, bounded memory


class BatchExecutor(Protocol):
    def map(self, fn: Callable[[Any], Any], chunks: Sequence[Any]) -> list[Any]:
        """fn applied to every chunk, results in order."""


class SerialBatchExecutor:
    """In this process (tests, small batches)."""

    def map(self, fn: Callable[[Any], Any], chunks: Sequence[Any]) -> list[Any]:
        return [fn(chunk) for chunk in chunks]


_WORKER_SOLVER: HMPCSolver | None = None


def _init_worker(spec: tuple[FeedbackLaw, RobotModel, HMPCConfig]) -> None:
    global _WORKER_SOLVER
    # One BLAS thread per process: the cores are already shared by the processes.
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    _WORKER_SOLVER = HMPCSolver(*spec)


def _solve_chunk(arrays: tuple[np.ndarray, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    assert _WORKER_SOLVER is not None, "worker not initialized"
    result = _WORKER_SOLVER.solve(*arrays)
    return result.tau_nm, result.status, result.tau_fb_nm


class ProcessPoolBatchExecutor:
    """A pool of worker processes, each holding its own solver (default: one per CPU)."""

    def __init__(self, workers: int | None = None) -> None:
        self.workers = workers or os.cpu_count() or 1
        self._pool: ProcessPoolExecutor | None = None
        self._spec: Any = None

    def start(self, spec: tuple[FeedbackLaw, RobotModel, HMPCConfig]) -> None:
        if self._pool is not None and self._spec is spec:
            return
        self.close()
        self._pool = ProcessPoolExecutor(self.workers, initializer=_init_worker, initargs=(spec,))
        self._spec = spec

    def map(self, fn: Callable[[Any], Any], chunks: Sequence[Any]) -> list[Any]:
        if self._pool is None:
            raise RuntimeError("ProcessPoolBatchExecutor.start(spec) first")
        return list(self._pool.map(fn, chunks))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __enter__(self) -> ProcessPoolBatchExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


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
    executor: BatchExecutor | None = None,
    chunk_states: int = DEFAULT_CHUNK_STATES,
) -> tuple[np.ndarray, np.ndarray]:
    """HMPC torques (B, N) and status (B,) for B independent states (cold start, no warm start).

    Each state is solved exactly as ``HMPCSolver.solve`` solves it alone (rows never interact), so
    the result does not depend on the chunking or the executor.
    """
    config = HMPCConfig() if config is None else config
    q = np.atleast_2d(np.asarray(q, float))
    if law_state is None:
        law_state = law.initial_state(q)
    arrays = [np.atleast_2d(np.asarray(a, float)) for a in (q, qd, q_d, qd_d, qdd_d, law_state)]
    batch = q.shape[0]
    if any(a.shape[0] != batch for a in arrays):
        raise ModelInputError(f"solve_batch: every array needs {batch} rows, got {[a.shape[0] for a in arrays]}")
    if chunk_states < 1:
        raise ModelInputError(f"solve_batch chunk_states: must be >= 1, got {chunk_states}")
    bounds = list(range(0, batch, chunk_states)) + [batch]
    chunks = [tuple(a[lo:hi] for a in arrays) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]
    if executor is None or isinstance(executor, SerialBatchExecutor):
        solver = HMPCSolver(law, robot, config)
        results: list[Any] = []
        for chunk in chunks:
            result: HMPCResult = solver.solve(*chunk)
            results.append((result.tau_nm, result.status, result.tau_fb_nm))
    else:
        start = getattr(executor, "start", None)
        if start is not None:
            start((law, robot, config))
        results = executor.map(_solve_chunk, chunks)
    return np.concatenate([r[0] for r in results]), np.concatenate([r[1] for r in results])
