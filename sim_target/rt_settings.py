"""Real-time settings of the target's physics thread: SCHED_FIFO, its own CPU, mlockall; the
start-up cost probe and its warning (:func:`start_realtime`); the CPUs of a free-running HIL run
(:func:`split_cpus`).

The same calls as the runtime's (hil_runtime/realtime.py), kept here because sim_target never
imports hil_runtime (docs/architecture.md). :func:`apply_thread_settings` acts on the *calling
thread* (Linux: ``sched_setscheduler(0, ...)`` and ``sched_setaffinity(0, ...)`` name the calling
thread), so the server applies it at the top of its loop; the control socket's thread, started
before, gets the same CPU one priority below (:func:`share_thread_settings`). A refused setting is
one warning; the target runs on without it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import gc
import logging
import os
from collections.abc import Sequence
from typing import Any

log = logging.getLogger(__name__)

_MCL_CURRENT = 1
_MCL_FUTURE = 2


def apply_thread_settings(
    fifo_priority: int, cpus: Sequence[int] | None, lock_memory: bool
) -> tuple[list[str], list[str]]:
    """Apply what is asked to the calling thread; returns (applied, refused) descriptions."""
    applied: list[str] = []
    refused: list[str] = []

    def note(what: str, error: str | None) -> None:
        if error is None:
            applied.append(what)
        else:
            refused.append(f"{what} ({error})")
            log.warning("target real time: %s refused: %s; carrying on without it", what, error)

    if cpus:
        try:
            os.sched_setaffinity(0, set(cpus))
            note(f"CPU {list(cpus)}", None)
        except (OSError, ValueError) as exc:
            note(f"CPU {list(cpus)}", getattr(exc, "strerror", None) or str(exc))
    if fifo_priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo_priority))
            note(f"SCHED_FIFO {fifo_priority}", None)
        except OSError as exc:
            note(f"SCHED_FIFO {fifo_priority}", exc.strerror or str(exc))
    if lock_memory:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
            err = ctypes.get_errno()
            note("mlockall", f"{errno.errorcode.get(err, err)}: {os.strerror(err)}")
        else:
            note("mlockall", None)
    return applied, refused


def share_thread_settings(native_id: int, fifo_priority: int, cpus: Sequence[int] | None) -> list[str]:
    """Give another thread of this process (kernel id ``native_id``) the physics thread's CPU and
    SCHED_FIFO one below it. A thread that can take the GIL (the control socket's) must not hold
    it while descheduled on a busy CPU: the physics thread would wait for it (milliseconds on a
    loaded machine, a whole period lost). On the physics thread's CPU, one priority below, it
    runs only while the physics thread sleeps, and at once when the physics thread waits for the
    GIL it holds. Returns what was refused (warned once each)."""
    refused: list[str] = []
    if cpus:
        try:
            os.sched_setaffinity(native_id, set(cpus))
        except OSError as exc:
            refused.append(f"control thread CPU {list(cpus)} ({exc.strerror})")
    if fifo_priority > 1:
        try:
            os.sched_setscheduler(native_id, os.SCHED_FIFO, os.sched_param(fifo_priority - 1))
        except OSError as exc:
            refused.append(f"control thread SCHED_FIFO {fifo_priority - 1} ({exc.strerror})")
    for what in refused:
        log.warning("target real time: %s refused; carrying on without it", what)
    return refused


def _apply(config: Any, control_thread_id: int | None) -> tuple[list[str], list[str]]:
    """``config.realtime`` on this thread and the control thread; start-up's objects frozen out of
    the garbage collector."""
    rt = config.realtime
    applied, refused = apply_thread_settings(rt.fifo_priority, rt.cpus, rt.lock_memory)
    if control_thread_id is not None:
        refused += share_thread_settings(control_thread_id, rt.fifo_priority, rt.cpus)
    gc.collect()
    gc.freeze()
    return applied, refused


def start_lockstep(config: Any, control_thread_id: int | None) -> dict[str, Any]:
    """``realtime.in_lockstep``: the same settings for the thread that serves the SYNCs (and steps
    the plant in them) and the control thread, gc frozen; no cost probe (lock-step has no deadline
    of its own). Returns the status's ``realtime`` entry."""
    applied, refused = _apply(config, control_thread_id)
    return {"applied": applied, "refused": refused}


_COST_PROBE_STEPS = 200  # physics steps timed at start-up
# A step costing more than this share of the period leaves too little for the bus and wake-up
# jitter: the target says at start-up that it cannot keep real time.
_COST_WARN_FRACTION = 0.5


def start_realtime(plant: Any, config: Any, control_thread_id: int | None) -> dict[str, Any]:
    """What ``clock: realtime`` does on the physics thread before its first tick: time the physics
    step (``plant.probe_step_cost_s``, the plant restored after) and warn on one line when it cannot
    keep the period; SCHED_FIFO / CPU / mlockall (``config.realtime``) for this thread and the
    control thread; freeze start-up's objects out of the garbage collector (a full collection of
    this process took milliseconds: never again). Returns the status's ``realtime`` entry."""
    period_s = config.period_s
    cost_s = plant.probe_step_cost_s(_COST_PROBE_STEPS)
    fraction = cost_s / period_s
    if fraction > _COST_WARN_FRACTION:
        log.warning(
            "target: cannot keep real time: one physics step (%d substeps) costs %.0f us, %.0f %% of "
            "the %g ms period; runs that fall behind are marked invalid (fewer plant.substeps helps)",
            plant.substeps,
            cost_s * 1e6,
            100 * fraction,
            period_s * 1e3,
        )
    applied, refused = _apply(config, control_thread_id)
    return {
        "plant_step_us": round(cost_s * 1e6, 1),
        "plant_step_fraction": round(fraction, 3),
        "substeps": plant.substeps,
        "applied": applied,
        "refused": refused,
    }


def split_cpus(spec: str = "auto") -> tuple[tuple[int, ...] | None, tuple[int, ...] | None]:
    """(runtime CPUs, target CPUs) for a free-running HIL run on this machine.

    ``auto``: the last CPU this process may use for the runtime's loop, the one before it for the
    target's physics (on a 2-core machine they then never share a core; with one CPU, no pinning);
    ``none``: no pinning; ``R,T``: CPU R for the runtime, T for the target. ValueError (one line)
    for anything else or a CPU this process may not use."""
    spec = spec.strip().lower()
    available = sorted(os.sched_getaffinity(0))
    if spec == "none":
        return None, None
    if spec == "auto":
        return ((available[-1],), (available[-2],)) if len(available) >= 2 else (None, None)
    parts = spec.split(",")
    try:
        runtime_cpu, target_cpu = (int(p) for p in parts)
    except ValueError:
        raise ValueError(f"--cpus: expected auto, none or RUNTIME,TARGET (two CPU numbers), got {spec!r}") from None
    for cpu in (runtime_cpu, target_cpu):
        if cpu not in available:
            raise ValueError(f"--cpus: CPU {cpu} is not one this process may use ({available})")
    return (runtime_cpu,), (target_cpu,)


__all__ = ["apply_thread_settings", "share_thread_settings", "split_cpus", "start_realtime"]
