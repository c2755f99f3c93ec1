"""What ``hil demo`` starts and creates, none of which may outlive it: child processes, the
signals around their start and stop, and the private directory.

Each child (the pybullet target, the runtime daemon) runs in its own session, so the terminal's
Ctrl-C reaches the demo alone and the demo stops the children in the order that keeps the arm
safe: the daemon first (it quick-stops the drives through the target), then the target. Each child
also gets ``PR_SET_PDEATHSIG`` = SIGTERM: should the demo itself be killed (SIGKILL, a crash), the
kernel sends the children SIGTERM, the stop path they handle. Their stderr goes to a log file
(never a pipe that nobody reads). The private directory (bus sockets, control sockets, configs)
names its owner's pid, so a later demo removes it when a killed demo could not.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

WORK_PREFIX = "hil-demo-"
OWNER_FILE = "demo.pid"  # the demo that owns a private directory (a SIGKILLed demo cannot remove its own)


class DemoError(RuntimeError):
    """A demo that cannot go on (a child failed to start, a fault): one line, exit code 1."""

    exit_code = 1


# Runs first in each child, then the CLI. Not a preexec_fn: forking a process that has threads
# (Zenoh's) and running Python before exec can deadlock. The demo holds SIGINT/SIGTERM blocked while
# it creates a child (exec keeps the mask): unblock them, or the child never sees its SIGTERM. Then
# ask the kernel for SIGTERM when the demo dies, and leave at once if it already has.
_CHILD_SHIM = """\
import ctypes, os, runpy, signal, sys
signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
try:
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
except (OSError, AttributeError):
    pass
if os.getppid() != int(os.environ["HIL_DEMO_PARENT_PID"]):
    sys.exit(1)
runpy.run_module("hil_runtime.cli", run_name="__main__", alter_sys=True)
"""


class Child:
    """One ``hil ...`` process (this interpreter) in its own session, stderr to ``log_path``."""

    def __init__(self, name: str, args: list[str], log_path: Path) -> None:
        self.name = name
        self.log_path = log_path
        self._log = open(log_path, "wb")  # noqa: SIM115 - closed in stop()
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "HIL_DEMO_PARENT_PID": str(os.getpid())}
        self.process = subprocess.Popen(
            [sys.executable, "-c", _CHILD_SHIM, *args],
            stdin=subprocess.DEVNULL,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,
        )
        self.pid = self.process.pid
        self.signalled_s: float | None = None  # when stop() sent SIGTERM
        self.exit_s: float | None = None  # how long from SIGTERM to exit

    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def last_lines(self, count: int = 3) -> str:
        lines = [line.strip() for line in self.log_text().splitlines() if line.strip()]
        return " | ".join(lines[-count:]) or "no output"

    def alive(self) -> bool:
        return self.process.poll() is None

    def wait_for_line(self, marker: str, timeout_s: float) -> None:
        """Wait until the child's log holds ``marker``; DemoError if it exits or times out first."""
        end = time.monotonic() + timeout_s
        while marker not in self.log_text():
            if not self.alive():
                raise DemoError(
                    f"{self.name} exited ({self.process.returncode}) before it was ready: {self.last_lines()}"
                )
            if time.monotonic() > end:
                raise DemoError(f"{self.name} not ready within {timeout_s:g} s: {self.last_lines()}")
            time.sleep(0.05)

    def stop(self, timeout_s: float) -> int:
        """SIGTERM (the child's clean stop), SIGKILL to its whole group after ``timeout_s``; the exit code."""
        if self.alive():
            self.signalled_s = time.monotonic()
            self._signal_group(signal.SIGTERM)
            try:
                self.process.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self._signal_group(signal.SIGKILL)
                self.process.wait(timeout=10)
            self.exit_s = time.monotonic() - self.signalled_s
        # Anything it started itself goes too (its session is its own process group).
        self._signal_group(signal.SIGKILL)
        with contextlib.suppress(OSError):
            self._log.close()
        return int(self.process.returncode)

    def _signal_group(self, sig: signal.Signals) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.pid, sig)


# --- signals while children start and stop ----------------------------------------------------------


@contextlib.contextmanager
def signals_blocked() -> Iterator[None]:
    """Hold SIGINT/SIGTERM while a child is being created and registered: a Ctrl-C then lands
    after the child is known, so the cleanup stops it (never a child nobody tracks)."""
    blocked = {signal.SIGINT, signal.SIGTERM}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, blocked)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


@contextlib.contextmanager
def terminate_raises_interrupt() -> Iterator[None]:
    """SIGTERM to the demo (a CI timeout, ``kill``) takes the same path as Ctrl-C."""
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def signals_ignored() -> Iterator[None]:
    """While the children are being stopped, a second Ctrl-C must not cut the stop short."""
    previous = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


# --- the private directory --------------------------------------------------------------------------


def make_work_dir() -> Path:
    """A new private directory owned by this process, after sweeping those of killed demos.

    Short (in the system's temporary directory): Unix socket paths are limited to ~107 bytes."""
    remove_stale_work_dirs()
    work = Path(tempfile.mkdtemp(prefix=WORK_PREFIX))
    (work / OWNER_FILE).write_text(str(os.getpid()))
    return work


def remove_stale_work_dirs() -> list[Path]:
    """Private directories of earlier demos that were killed (SIGKILL leaves no chance to clean up):
    removed when their owner is gone. Their children are gone too (PR_SET_PDEATHSIG)."""
    removed = []
    for directory in Path(tempfile.gettempdir()).glob(f"{WORK_PREFIX}*"):
        try:
            if directory.stat().st_uid != os.getuid():
                continue
            owner = int((directory / OWNER_FILE).read_text())
        except (OSError, ValueError):
            continue
        try:
            os.kill(owner, 0)
            continue  # still running
        except ProcessLookupError:
            pass
        except PermissionError:
            continue
        shutil.rmtree(directory, ignore_errors=True)
        removed.append(directory)
    return removed


__all__ = [
    "OWNER_FILE",
    "WORK_PREFIX",
    "Child",
    "DemoError",
    "make_work_dir",
    "remove_stale_work_dirs",
    "signals_blocked",
    "signals_ignored",
    "terminate_raises_interrupt",
]
