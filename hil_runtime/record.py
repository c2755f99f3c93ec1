"""The record of a run: what :meth:`hil_runtime.runtime.Runtime.run` kept per cycle and returns.

:class:`RunRecord` is preallocated (``capacity`` rows, one row per ACTIVE cycle, written from the
loop's :class:`~hil_runtime.telemetry.sink.CycleState`); ``hil run --record`` saves it as .npz.
:class:`RunResult` says why a run ended, with its counters.
"""

from __future__ import annotations

import contextlib
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil_runtime.lifecycle import LifecycleState
from hil_runtime.telemetry.sink import CycleState

MAX_RECORD_CYCLES = 3_600_000  # an hour at 1 kHz, ~1.2 GB preallocated (~330 B a row); hil run --record-cycles


class RunRecord:
    """Preallocated per-cycle arrays (``capacity`` rows); rows past it are counted, not kept."""

    FIELDS = ("q", "qd", "q_ref", "qd_ref", "tau", "tau_fb")

    def __init__(self, capacity: int, n_joints: int) -> None:
        self.capacity = capacity
        self.n = 0
        self.overflow = 0
        self.t_s = np.zeros(capacity)  # reference time of the row: period index x period
        self.wall_s = np.zeros(capacity)  # monotonic clock at the cycle's start, from activation
        self.q = np.zeros((capacity, n_joints))
        self.qd = np.zeros((capacity, n_joints))
        self.q_ref = np.zeros((capacity, n_joints))
        self.qd_ref = np.zeros((capacity, n_joints))
        self.tau = np.zeros((capacity, n_joints))  # the command the supervisor chose
        self.tau_fb = np.zeros((capacity, n_joints))
        self.fallback = np.zeros(capacity)
        self.compute_s = np.zeros(capacity)  # feedback to set-points (hil_runtime.loop: one meaning)
        self.exchange_s = np.zeros(capacity)  # this cycle's wait on the bus

    def add(self, sample: CycleState, t_s: float, wall_s: float, exchange_s: float) -> int:
        """Store one row; returns its index (-1 when full)."""
        i = self.n
        if i >= self.capacity:
            self.overflow += 1
            return -1
        self.t_s[i] = t_s
        self.wall_s[i] = wall_s
        self.q[i] = sample.q
        self.qd[i] = sample.qd
        self.q_ref[i] = sample.q_ref
        self.qd_ref[i] = sample.qd_ref
        self.tau[i] = sample.tau
        self.tau_fb[i] = sample.tau_fb
        self.fallback[i] = sample.fallback
        self.compute_s[i] = sample.compute_s
        self.exchange_s[i] = exchange_s
        self.n = i + 1
        return i

    def arrays(self) -> dict[str, np.ndarray]:
        """The filled rows (views)."""
        n = self.n
        names = ("t_s", "wall_s", *self.FIELDS, "fallback", "compute_s", "exchange_s")
        return {name: getattr(self, name)[:n] for name in names}

    def save_npz(self, path: Path | str) -> None:
        """Written whole or not at all (a temporary name, then a rename): never half a file."""
        from hil_runtime.outputs import atomic_path

        # Through an open file: np.savez appends '.npz' to a name without it, and the renamed file
        # would then be missing while the written one stayed behind as a hidden partial file.
        # Any values: numpy's stub types savez_compressed's **kwds as also reaching its bool allow_pickle.
        arrays: dict[str, Any] = self.arrays()
        with atomic_path(path) as tmp, open(tmp, "wb") as handle:
            np.savez_compressed(handle, **arrays)
            handle.flush()
            with contextlib.suppress(OSError):  # a pipe or a special file cannot be synced
                os.fsync(handle.fileno())


@dataclass
class RunResult:
    """What :meth:`Runtime.run` returns: why it ended and the counters of the run."""

    reason: str  # "stop", "cycles", "duration", "fault"
    state: LifecycleState
    fault: str | None
    cycles: int
    stats: dict[str, Any]
    fault_cycle: int | None = None  # exchanges in ACTIVE when the last fault was entered


RECORD_SUFFIXES = {".npz": "npz", ".mcap": "mcap"}


def check_record_path(path: Path, option: str = "--record") -> str:
    """Before the run: the record's format from its suffix (``npz`` or ``mcap``), its directory
    created and proved writable (a probe file), no directory, device, FIFO or socket in its place
    (``/dev/full``: the record would be lost after the run). OutputError (one line, exit 2) otherwise."""
    from hil_runtime.outputs import OutputError, prepare_output_dir

    kind = RECORD_SUFFIXES.get(path.suffix.lower())
    if kind is None:
        known = ", ".join(RECORD_SUFFIXES)
        raise OutputError(f"{option} {path}: unknown record format {path.suffix or '(no suffix)'!r} (use {known})")
    if path.is_dir():
        raise OutputError(f"{option} {path}: a directory is in the way")
    if path.exists() and not stat.S_ISREG(path.stat().st_mode):
        raise OutputError(f"{option} {path}: not a regular file (a device, FIFO or socket is in the way)")
    prepare_output_dir(path.parent if str(path.parent) else Path("."), option=option)
    return kind
