"""Real-time hygiene where the OS allows it; where it refuses, one warning and carry on.

- :func:`lock_memory`: ``mlockall(MCL_CURRENT | MCL_FUTURE)`` through ctypes (no page faults in
  the loop; needs ``LimitMEMLOCK=infinity`` under systemd or CAP_IPC_LOCK).
- :func:`set_thread_fifo` / :func:`set_thread_affinity`: SCHED_FIFO and CPU affinity for the
  *calling thread only* (``os.sched_setscheduler(0, ...)`` acts on the calling thread on Linux).
  Threads created afterwards inherit them, so the runtime starts its helper threads first.
- :func:`keep_other_threads_off`: every other thread of the process (publisher, bus receive,
  Zenoh's and onnxruntime's own) moved off the loop's CPUs, where the machine has others; they
  keep SCHED_OTHER (created before the loop thread took SCHED_FIFO).
- :func:`freeze_heap` / :class:`GcQuiet`: ``gc.collect(); gc.freeze()`` before the drives are
  enabled (the survivors are never scanned again) and ``gc.disable()`` while ACTIVE, so no
  collection pauses the loop; re-enabled after.

Each returns whether it took effect; :class:`RealtimeReport` collects what happened for the logs
and the docs' figures.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import gc
import logging
import os
import threading
from dataclasses import dataclass, field
from typing import Self

log = logging.getLogger(__name__)

MCL_CURRENT = 1
MCL_FUTURE = 2


@dataclass
class RealtimeReport:
    applied: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)

    def note(self, what: str, ok: bool, why: str = "") -> bool:
        if ok:
            self.applied.append(what)
        else:
            self.refused.append(f"{what} ({why})" if why else what)
            log.warning("real time: %s refused%s; carrying on without it", what, f": {why}" if why else "")
        return ok


def lock_memory(report: RealtimeReport | None = None) -> bool:
    report = report or RealtimeReport()
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    except OSError as exc:
        return report.note("mlockall", False, str(exc))
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
        err = ctypes.get_errno()
        return report.note("mlockall", False, f"{errno.errorcode.get(err, err)}: {os.strerror(err)}")
    return report.note("mlockall", True)


def set_thread_fifo(priority: int, report: RealtimeReport | None = None) -> bool:
    report = report or RealtimeReport()
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        return report.note(f"SCHED_FIFO {priority}", False, getattr(exc, "strerror", None) or str(exc))
    return report.note(f"SCHED_FIFO {priority}", True)


def set_thread_affinity(cpus: tuple[int, ...], report: RealtimeReport | None = None) -> bool:
    report = report or RealtimeReport()
    try:
        os.sched_setaffinity(0, set(cpus))
    except (OSError, ValueError, AttributeError) as exc:
        return report.note(f"CPU affinity {list(cpus)}", False, getattr(exc, "strerror", None) or str(exc))
    return report.note(f"CPU affinity {list(cpus)}", True)


def keep_other_threads_off(cpus: tuple[int, ...], report: RealtimeReport | None = None) -> bool:
    """Move every thread of this process but the calling one off ``cpus`` (the loop's) onto the
    machine's other CPUs, when it has any; threads created later inherit their creator's affinity."""
    report = report or RealtimeReport()
    try:
        # The machine's CPUs, not the caller's affinity: a second runtime on a thread already
        # pinned (the daemon's main thread, a benchmark's) still finds the others.
        others = set(range(os.cpu_count() or 1)) - set(cpus)
        if not others:
            return report.note("helper threads off the loop's CPU", False, "no other CPU")
        me = threading.get_native_id()
        for name in os.listdir("/proc/self/task"):
            tid = int(name)
            if tid != me:
                with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile
                    os.sched_setaffinity(tid, others)
    except (OSError, ValueError, AttributeError) as exc:
        return report.note("helper threads off the loop's CPU", False, getattr(exc, "strerror", None) or str(exc))
    return report.note(f"helper threads on CPU {sorted(others)}", True)


def clock_pacing_risk(period_s: float, fifo_applied: bool) -> str | None:
    """Why clock pacing may not hold ``period_s`` here, or None: no SCHED_FIFO on the loop thread
    and a load average at or above the CPU count. Said once, as a warning, before ACTIVE: the loop
    then overruns (counted, skipped), the drives hold a stale torque meanwhile, and the arm may
    reach a safety limit, which FAULTs the run as it must (docs/runtime.md, real-time hygiene)."""
    if fifo_applied:
        return None
    try:
        load = os.getloadavg()[0]
    except OSError:  # no load average on this system: nothing to say
        return None
    cpus = os.cpu_count() or 1
    if load < cpus:
        return None
    return (
        f"clock pacing at {1.0 / period_s:.0f} Hz without SCHED_FIFO on a loaded machine (load average "
        f"{load:.1f} on {cpus} CPUs): expect overruns, during which the drives hold a stale torque; for a "
        "deterministic run use loop.pacing: bus against a lock-stepped target, or grant LimitRTPRIO"
    )


def freeze_heap() -> None:
    """Collect once, then move every survivor to the permanent generation (never scanned again).
    Tens of milliseconds with a large heap: call it before the drives are enabled, never between
    two exchanges (the drives quick-stop when their set-points stop for comm_loss_timeout_s)."""
    gc.collect()
    gc.freeze()


class GcQuiet:
    """``with GcQuiet():`` no garbage collection inside (:func:`freeze_heap` first, outside)."""

    def __enter__(self) -> Self:
        self._was_enabled = gc.isenabled()
        gc.disable()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._was_enabled:
            gc.enable()
