"""The executor interface that dataset generation and labeling run through.

The science code calls ``executor.map(fn, tasks)`` with a top-level (picklable) ``fn`` and
picklable tasks, and gets the results in order. Local processes are the default; a distributed
engine (e.g. Ray: ``ray.get([ray.remote(fn).remote(t) for t in tasks])``) implements the same one
method later without touching the science code.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Protocol


class Executor(Protocol):
    def map(self, fn: Callable[[Any], Any], tasks: Sequence[Any]) -> Iterator[Any]:
        """fn(task) for every task, yielded in order."""


class SerialExecutor:
    """In this process (tests, debugging)."""

    def map(self, fn: Callable[[Any], Any], tasks: Sequence[Any]) -> Iterator[Any]:
        for task in tasks:
            yield fn(task)


def _single_thread_worker() -> None:
    # The processes already share the cores; nested BLAS/torch threads would oversubscribe them.
    os.environ["OMP_NUM_THREADS"] = "1"
    os.environ["OPENBLAS_NUM_THREADS"] = "1"


class LocalProcessExecutor:
    """A pool of local worker processes (default: one per CPU)."""

    def __init__(self, workers: int | None = None) -> None:
        self.workers = max(1, workers or os.cpu_count() or 1)

    def map(self, fn: Callable[[Any], Any], tasks: Sequence[Any]) -> Iterator[Any]:
        if self.workers == 1 or len(tasks) <= 1:
            yield from SerialExecutor().map(fn, tasks)
            return
        with ProcessPoolExecutor(self.workers, initializer=_single_thread_worker) as pool:
            yield from pool.map(fn, tasks)


def make_executor(workers: int | None) -> Executor:
    """``workers`` 1: serial; None: one process per CPU."""
    return SerialExecutor() if workers == 1 else LocalProcessExecutor(workers)
