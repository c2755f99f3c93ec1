"""One executor interface for the models' embarrassingly parallel work: dataset simulation, HMPC
labeling, emulator training runs.

The science code calls ``executor.map(fn, tasks)`` with a top-level (picklable) ``fn`` and picklable
tasks and gets ``fn(task)`` for every task, in task order, whatever the backend::

    with make_executor("local", workers=2) as executor:
        results = list(executor.map(fn, tasks))

Backends (``EXECUTORS``): ``serial`` (this process), ``local`` (a pool of local processes, the
default) and ``ray`` (a local Ray instance bound to 127.0.0.1, no dashboard, no usage stats; the
``ray`` extra). State that is costly to build and the same for many tasks (an HMPC solver) is built
once per worker process with ``worker_cached(key, factory)``, so it works on every backend.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from abc import ABC, abstractmethod
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

from models.errors import ModelInputError

EXECUTORS = ("serial", "local", "ray")
DEFAULT_EXECUTOR = "local"

# Environment of every worker process: the processes already share the cores, nested BLAS/torch
# threads would oversubscribe them.
SINGLE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


class Executor(ABC):
    """``map(fn, tasks)``: fn(task) for every task, yielded in task order; ``close()`` frees the workers."""

    name: str = ""
    workers: int = 1

    @abstractmethod
    def map(self, fn: Callable[[Any], Any], tasks: Sequence[Any]) -> Iterator[Any]:
        """fn(task) for every task, yielded in order."""

    def close(self) -> None:  # noqa: B027 - a hook: backends without workers have nothing to release
        """Release the workers (idempotent); the executor can be used again afterwards."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(workers={self.workers})"


class SerialExecutor(Executor):
    """In this process (tests, debugging, one worker)."""

    name = "serial"

    def map(self, fn: Callable[[Any], Any], tasks: Sequence[Any]) -> Iterator[Any]:
        for task in tasks:
            yield fn(task)


def _single_thread_worker() -> None:
    os.environ.update(SINGLE_THREAD_ENV)


class LocalProcessExecutor(Executor):
    """A pool of local worker processes (default: one per CPU), started at the first ``map`` and
    kept until ``close()``, so per-worker state (``worker_cached``) survives between calls. One
    worker or one task: in this process."""

    name = "local"

    def __init__(self, workers: int | None = None) -> None:
        self.workers = max(1, workers or os.cpu_count() or 1)
        self._pool: ProcessPoolExecutor | None = None

    def map(self, fn: Callable[[Any], Any], tasks: Sequence[Any]) -> Iterator[Any]:
        if self.workers == 1 or len(tasks) <= 1:
            yield from SerialExecutor().map(fn, tasks)
            return
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.workers, initializer=_single_thread_worker)
        yield from self._pool.map(fn, tasks)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None


# --- ray -------------------------------------------------------------------------------------
# Set in this process while Ray starts; its processes (GCS, raylet, dashboard head, workers) are
# started then and inherit them:
# - no usage statistics, no prompt about them;
# - RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0: Ray's single-machine mode, where "127.0.0.1" stays the
#   node address (otherwise Ray replaces it with the outbound interface's address and its gRPC
#   servers listen there); it is read when ray is imported;
# - HTTP(S) through a closed loopback port: even with the dashboard and usage stats off, the
#   minimal dashboard head probes cloud metadata servers (169.254.169.254, metadata.google.internal)
#   over HTTP; with this proxy those requests fail on 127.0.0.1 and nothing leaves the machine.
_CLOSED_LOOPBACK_PROXY = "http://127.0.0.1:9"
RAY_ENV = {
    "RAY_USAGE_STATS_ENABLED": "0",
    "RAY_USAGE_STATS_PROMPT_ENABLED": "0",
    "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0",
    "http_proxy": _CLOSED_LOOPBACK_PROXY,
    "https_proxy": _CLOSED_LOOPBACK_PROXY,
    "HTTP_PROXY": _CLOSED_LOOPBACK_PROXY,
    "HTTPS_PROXY": _CLOSED_LOOPBACK_PROXY,
    "no_proxy": "127.0.0.1,localhost,::1",
    "NO_PROXY": "127.0.0.1,localhost,::1",
    **SINGLE_THREAD_ENV,
}
LOOPBACK = "127.0.0.1"
OBJECT_STORE_BYTES = 1 << 30  # tasks and results are small arrays; Ray's default takes 30 % of the RAM


@contextlib.contextmanager
def _sigint_blocked() -> Iterator[None]:
    """SIGINT blocked while Ray starts its processes: they inherit the mask, so a Ctrl-C on the
    terminal (sent to the whole process group) reaches only this process, which then shuts Ray down
    in order (``close``); Ray's processes, hit directly, die mid-protocol and the driver crashes on
    exit. A Ctrl-C during the start is delivered when the start returns."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


@contextlib.contextmanager
def _environment(values: dict[str, str]) -> Iterator[None]:
    saved = {key: os.environ.get(key) for key in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


class RayExecutor(Executor):
    """A local Ray instance with ``workers`` CPUs, started at the first ``map`` (bound to 127.0.0.1,
    no dashboard, no usage statistics) and shut down by ``close()``. Tasks run once (no retries),
    so a failure surfaces as the task's own exception."""

    name = "ray"

    def __init__(self, workers: int | None = None) -> None:
        self.workers = max(1, workers or os.cpu_count() or 1)
        self._ray: Any = None
        self._remote: dict[Callable[[Any], Any], Any] = {}

    def _start(self) -> Any:
        if self._ray is not None:
            return self._ray
        # Token authentication between Ray's processes, as Ray itself sets it (for good, in this
        # process) for a new local cluster; set here, Ray does not print its one-line notice about it.
        os.environ.setdefault("RAY_AUTH_MODE", "token")
        with _environment(RAY_ENV):
            try:
                import ray
            except ImportError:
                raise ModelInputError(
                    "--executor ray: ray is not installed (pip install -c constraints.txt -e '.[ray]')"
                ) from None
            if ray.is_initialized():
                raise ModelInputError("--executor ray: Ray already runs in this process; it starts its own")
            # Imported earlier without RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0: Ray would advertise and
            # listen on the outbound interface instead of 127.0.0.1. Refuse before anything starts.
            if getattr(ray._private.ray_constants, "ENABLE_RAY_CLUSTER", True):
                raise ModelInputError(
                    "--executor ray: ray was imported before models.executors could pin it to 127.0.0.1; "
                    "set RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 in the environment"
                )
            with _sigint_blocked():
                context = ray.init(
                    address="local",
                    num_cpus=self.workers,
                    include_dashboard=False,
                    _node_ip_address=LOOPBACK,
                    object_store_memory=OBJECT_STORE_BYTES,
                    log_to_driver=False,
                    configure_logging=False,
                )
        node_ip = context.address_info.get("node_ip_address")
        if node_ip != LOOPBACK:  # never run on a non-loopback address
            ray.shutdown()
            raise ModelInputError(f"--executor ray: Ray bound to {node_ip}, not {LOOPBACK}; stopped")
        self._ray = ray
        return ray

    def map(self, fn: Callable[[Any], Any], tasks: Sequence[Any]) -> Iterator[Any]:
        ray = self._start()
        remote = self._remote.get(fn)
        if remote is None:
            remote = self._remote[fn] = ray.remote(num_cpus=1, max_retries=0)(fn)
        refs = [remote.remote(task) for task in tasks]
        # On Ctrl-C or a failed task the remaining tasks are neither waited for nor cancelled:
        # ray.cancel(force=True) on a task that finishes meanwhile aborts the driver in Ray 2.60
        # (task_manager.cc "Tried to complete task that was not pending", seen in CI); close() shuts
        # Ray down, which ends them.
        for ref in refs:
            try:
                value = ray.get(ref)
            except ray.exceptions.RayTaskError as exc:
                # The task's own exception, as the other executors raise it (a user error stays
                # one line); Ray's report, with the worker's traceback, is chained to it.
                if isinstance(exc.cause, Exception):
                    raise exc.cause from exc
                raise
            yield value

    def close(self) -> None:
        if self._ray is not None:
            self._ray.shutdown()
            self._ray = None
            self._remote.clear()


def make_executor(name: str = DEFAULT_EXECUTOR, workers: int | None = None) -> Executor:
    """The executor ``name`` (``EXECUTORS``) with ``workers`` workers (None: one per CPU)."""
    if name not in EXECUTORS:
        raise ModelInputError(f"--executor: unknown '{name}' (known: {', '.join(EXECUTORS)})")
    if workers is not None and workers < 1:
        raise ModelInputError(f"--workers: must be >= 1, got {workers}")
    if name == "serial":
        return SerialExecutor()
    if name == "ray":
        return RayExecutor(workers)
    return LocalProcessExecutor(workers)


# --- per-worker state ------------------------------------------------------------------------
_WORKER_CACHE: OrderedDict[str, Any] = OrderedDict()
WORKER_CACHE_SIZE = 4  # e.g. the solvers of the laws labeled last


def worker_cached(key: str, factory: Callable[[], Any]) -> Any:
    """``factory()`` built once per worker process (and in this process for serial runs) per ``key``;
    the few most recent kept. ``key`` must identify what the factory builds (e.g. a hash of its spec)."""
    if key in _WORKER_CACHE:
        _WORKER_CACHE.move_to_end(key)
        return _WORKER_CACHE[key]
    value = factory()
    _WORKER_CACHE[key] = value
    while len(_WORKER_CACHE) > WORKER_CACHE_SIZE:
        _WORKER_CACHE.popitem(last=False)
    return value


__all__ = [
    "DEFAULT_EXECUTOR",
    "EXECUTORS",
    "Executor",
    "LocalProcessExecutor",
    "RayExecutor",
    "SerialExecutor",
    "make_executor",
    "worker_cached",
]
