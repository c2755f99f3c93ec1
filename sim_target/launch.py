"""Start the HIL target for a program that drives it (``hil experiment --plant hil``, tests, benchmarks).

One interface, three transports::

    with launch_target(config_dict, transport="virtual") as target:   # this process, python-can virtual
        target.transport          # the runtime's bus transport section (interface, channel, fd, ...)
        target.start_run(start)   # sim_target.config.RunStart: place the arm, restart time, schedule faults
        target.status()           # steps, syncs, time, position, ...

- ``virtual``: the target in this process on a private python-can ``virtual`` channel, its
  lock-step clock in a thread (fast, deterministic; the GIL is shared with the caller).
- ``ipc``: ``hil target serve`` in a child process on the project's ipc bus (drivers/ipc: Unix
  sockets in a private directory; docs/ipc_bus.md).
- ``bridge``: ``hil target serve`` in a child process, its virtual bus served by the
  python-can-remote bridge on 127.0.0.1 at a port the OS picks.

The child processes are controlled through the target's control socket (sim_target/control.py)
and stopped with SIGTERM; nothing listens on any address but loopback.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import yaml

from sim_target.config import RunStart, TargetConfig, TargetConfigError, parse_target_config
from sim_target.control import send_control

if TYPE_CHECKING:
    from sim_target.server import TargetServer

Transport = Literal["virtual", "ipc", "bridge"]
TRANSPORTS: tuple[str, ...] = ("virtual", "ipc", "bridge")
CAN_FD = {"fd": True, "data_bitrate": 5_000_000}  # six drives above ~420 Hz need CAN FD
_BUS_RATES = ("fd", "bitrate", "data_bitrate")


def can_fd(n_drives: int) -> dict[str, Any]:
    """CAN FD rates that carry ``n_drives`` at 1 kHz within the bus-load budget: a 5 Mbit/s data
    phase up to six drives (79 %), 8 Mbit/s, CAN FD's usual top rate, beyond (7 drives: 92 % at 5)."""
    return CAN_FD if n_drives <= 6 else {"fd": True, "data_bitrate": 8_000_000}


def _runtime_rates(config: dict[str, Any]) -> dict[str, Any]:
    """The runtime's bus rates: the target's own (the two ends of one bus), else CAN_FD."""
    return {**CAN_FD, **{k: v for k, v in config.get("bus", {}).items() if k in _BUS_RATES}}


START_TIMEOUT_S = 60.0  # a loaded machine imports pybullet, onnx, ... slowly


class TargetLaunchError(RuntimeError):
    """The target did not come up (one line, exit 2)."""

    exit_code = 2


class LaunchedTarget:
    """A running target, whichever the transport: what a driving program needs from it."""

    def __init__(
        self,
        transport: dict[str, Any],
        server: Any = None,
        control_socket: Path | None = None,
        process: subprocess.Popen[str] | None = None,
    ) -> None:
        self.transport = transport  # drivers.config.TransportConfig fields for the runtime's bus
        self.server = server  # the TargetServer (virtual only)
        self.control_socket = control_socket
        self.process = process

    def start_run(self, start: RunStart) -> None:
        """Arm a run start (checked by the target; TargetConfigError if it refuses)."""
        if self.server is not None:
            self.server.start_run(start)
            return
        reply = self._control(start.model_dump(mode="json"))
        if not reply.get("ok"):
            raise TargetConfigError(f"target refused the run start: {reply.get('error', 'no reason given')}")

    def status(self) -> dict[str, Any]:
        if self.server is not None:
            return dict(self.server.status())
        return self._control({"kind": "status"})

    def _control(self, command: dict[str, Any]) -> dict[str, Any]:
        assert self.control_socket is not None
        if self.process is not None and self.process.poll() is not None:
            raise TargetLaunchError(f"the target process exited ({self.process.returncode})")
        return send_control(self.control_socket, command, timeout_s=10.0)


def target_config_dict(robot: str, period_s: float, substeps: int, **extra: Any) -> dict[str, Any]:
    """A lock-stepped target for ``robot`` (drives 1..6 by default), ``extra`` merged on top."""
    return {
        "robot": robot,
        "period_s": period_s,
        "clock": "lockstep",
        "bus": {"interface": "virtual", **CAN_FD},
        "plant": {"substeps": substeps},
        **extra,
    }


@contextlib.contextmanager
def launch_target(
    config: dict[str, Any], transport: Transport = "virtual", work_dir: Path | None = None
) -> Iterator[LaunchedTarget]:
    """The target of ``config`` (a target config mapping; its ``bus`` section is set here)."""
    if transport not in TRANSPORTS:
        raise TargetLaunchError(f"transport: unknown '{transport}' (known: {', '.join(TRANSPORTS)})")
    if transport == "virtual":
        with _in_process(config) as target:
            yield target
        return
    own_dir = work_dir is None
    # A short private directory: Unix socket paths are limited to ~107 bytes.
    directory = Path(tempfile.mkdtemp(prefix="hil-")) if work_dir is None else Path(work_dir)
    try:
        with _child_process(config, transport, directory) as target:
            yield target
    finally:
        if own_dir:
            shutil.rmtree(directory, ignore_errors=True)


@contextlib.contextmanager
def serve_in_thread(config: TargetConfig) -> Iterator[TargetServer]:
    """The target of ``config`` in this process, its lock-step clock in a thread; stopped and closed after."""
    from sim_target.server import build_server

    server, close = build_server(config)
    runner = threading.Thread(target=server.run, name="target", daemon=True)
    runner.start()
    try:
        yield server
    finally:
        server.stop()
        runner.join(timeout=10)
        close()


@contextlib.contextmanager
def _in_process(config: dict[str, Any]) -> Iterator[LaunchedTarget]:
    channel = f"hil-{uuid.uuid4().hex[:8]}"
    bus = {**config.get("bus", {}), "interface": "virtual", "channel": channel}
    with serve_in_thread(parse_target_config({**config, "bus": bus}, "target")) as server:
        yield LaunchedTarget({**_runtime_rates(config), "interface": "virtual", "channel": channel}, server=server)


@contextlib.contextmanager
def _child_process(config: dict[str, Any], transport: str, directory: Path) -> Iterator[LaunchedTarget]:
    sock = directory / "target.sock"
    data = {**config, "control_socket": str(sock)}
    if transport == "ipc":
        bus_dir = directory / "bus"
        data["bus"] = {**config.get("bus", {}), "interface": "ipc", "channel": str(bus_dir)}
        runtime_transport: dict[str, Any] = {**_runtime_rates(config), "interface": "ipc", "channel": str(bus_dir)}
    else:
        data["bus"] = {**config.get("bus", {}), "interface": "virtual", "channel": "hil"}
        data["bridge"] = {"host": "127.0.0.1", "port": 0}
        runtime_transport = {**_runtime_rates(config), "interface": "remote"}
    parse_target_config(data, "target")  # refuse here, with one line, rather than in the child
    path = directory / "target.yaml"
    path.write_text(yaml.safe_dump(data))
    process = start_hil("target", "serve", "--config", str(path))
    try:
        url = bridge_url(wait_ready(process)) if transport == "bridge" else ""
        if url is None:
            raise TargetLaunchError("hil target serve is up but names no bridge URL")
        # Keep reading stderr so the child never blocks on a full pipe.
        threading.Thread(target=_drain, args=(process,), daemon=True).start()
        if transport == "bridge":
            runtime_transport["channel"] = url
        yield LaunchedTarget(runtime_transport, control_socket=sock, process=process)
    finally:
        _stop(process)


# --- child processes of the ``hil`` command -----------------------------------------------------------


def hil_command(*args: str) -> list[str]:
    """The argv of ``hil ARGS...`` with this interpreter (the installed console script may be absent)."""
    return [sys.executable, "-m", "hil_runtime.cli", *args]


def start_hil(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    """``hil ARGS...`` as a child process, stdout discarded, stderr piped as text (its one-line
    messages and ready lines); unbuffered, so a line arrives when it is written."""
    return subprocess.Popen(
        hil_command(*args),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env={**(os.environ if env is None else env), "PYTHONUNBUFFERED": "1"},
    )


def wait_ready(process: subprocess.Popen[str], timeout_s: float = START_TIMEOUT_S) -> str:
    """Read ``hil target serve``'s stderr up to its ready line (``target serving ...``) and return
    it; the rest stays in the pipe. TargetLaunchError, with the last lines, when it exits first."""
    assert process.stderr is not None
    lines: list[str] = []
    timer = threading.Timer(timeout_s, process.kill)
    timer.start()
    try:
        for line in process.stderr:
            lines.append(line)
            if "target serving" in line:
                return line
    finally:
        timer.cancel()
    process.wait(timeout=10)
    tail = " | ".join(x.strip() for x in lines[-3:])
    raise TargetLaunchError(f"hil target serve did not start (exit {process.returncode}): {tail}")


def bridge_url(ready_line: str) -> str | None:
    """The python-can-remote bridge's URL in a ready line (with the port the OS picked), or None."""
    found = re.search(r"bridge (ws://127\.0\.0\.1:\d+/)", ready_line)
    return found.group(1) if found else None


def _drain(process: subprocess.Popen[str]) -> None:
    assert process.stderr is not None
    for _ in process.stderr:
        pass


def _stop(process: subprocess.Popen[str], timeout_s: float = 10.0) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


__all__ = [
    "TRANSPORTS",
    "LaunchedTarget",
    "TargetLaunchError",
    "Transport",
    "bridge_url",
    "hil_command",
    "launch_target",
    "serve_in_thread",
    "start_hil",
    "target_config_dict",
    "wait_ready",
]
