"""``hil demo``: the runtime driving the emulated arm, as separate processes, watched live.

    target = hil target serve     (pybullet UR5 behind six emulated CiA 402 drives)
       ▲ │  ipc bus (Unix sockets in a private directory), CAN FD frames, 1 ms SYNC
       │ ▼
    runtime = hil run             (the daemon: policy bundle, supervisor, telemetry)
       │  Zenoh on 127.0.0.1, a free port (the runtime connects to the demo's session)
       ▼
    this process                  (live view, the recording, then the simulation twin and the report)

The target places the arm on the condition's initial state when the drives are enabled and
injects the condition's disturbance (a RunStart, as ``hil experiment --plant hil``); the runtime
tracks the condition from its t = 0. When the run has covered the condition, the daemon is stopped
as systemd stops it (SIGTERM: quick stop, disable, exit 0), the drives are checked stopped at the
target, the target is stopped, and the private directory (bus sockets, control sockets, configs)
is removed. The same stop runs on Ctrl-C or any error, at any moment (try/finally; the children
run in their own sessions and die with the demo: models/demo/processes.py). docs/demo.md.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from models.demo.processes import Child, DemoError, free_loopback_port
from models.errors import ModelInputError

#: The best LMPC law of Table I (README, docs/lmpc.md): the lowest LMPC composite score, MRAC 0.025
#: (PD 0.031, PID 0.031, ADRC 0.043, SMC 0.045, H∞ 0.047; structured bundles). Lower is better.
BEST_LMPC_LAW = "mrac"
DEFAULT_CONDITION = "C1"
MODES = ("lmpc", "fb")
START_TIMEOUT_S = 180.0  # a fresh machine imports pybullet, onnxruntime, zenoh for the first time
STOP_TIMEOUT_S = 20.0  # SIGTERM -> exit; the quick stop waits at most the bus's state_change_timeout_s
TARGET_STOP_TIMEOUT_S = 10.0  # the target closes its bus and sockets in well under a second
WORK_PREFIX = "hil-demo-"
OWNER_FILE = "demo.pid"  # the demo that owns a private directory (a SIGKILLed demo cannot remove its own)
STALL_S = 30.0  # ACTIVE without a cycle for this long: the rig is stuck (the drives stop on their own)
POLL_S = 0.1  # the control socket's status: progress, FAULT


@dataclass(frozen=True)
class DemoOptions:
    law: str = BEST_LMPC_LAW
    mode: str = "lmpc"  # lmpc: the fused law + emulator bundle; fb: the bundle's law alone
    condition: str = DEFAULT_CONDITION
    duration_s: float | None = None  # None: the condition's own (5 s for the paper's)
    realtime: bool = False  # free-running: the target on its own clock, the runtime on absolute deadlines
    target_substeps: int = 32  # pybullet steps per control period
    robot: str = "ur5_paper"


@dataclass
class HilOutcome:
    """What the HIL part of the demo produced, kept in memory: the private directory is gone."""

    record: dict[str, np.ndarray]  # the runtime's own per-cycle record (hil run --record)
    schema: Any  # hil_runtime.telemetry.codec.Schema
    state_payloads: list[bytes]
    status_payloads: list[bytes]
    event_payloads: list[bytes]
    stats_payloads: list[bytes]
    documents: dict[str, Any]  # the runtime's config and bundle summary (telemetry queryables)
    endpoint: str
    fault: str | None
    shutdown: dict[str, Any]
    processes: dict[str, Any]
    wall_s: dict[str, float]
    logs: dict[str, str]
    work_dir: str
    period_s: float


@dataclass
class DemoPhase:
    """What the live view shows besides the telemetry: the demo's own progress."""

    text: str = "starting"
    t_s: float = 0.0  # the run's time (simulated in lock-step, wall in real time)
    duration_s: float = 0.0
    watch: Any = None  # the telemetry watch state, once the schema is known
    robot: str = ""
    joints: tuple[str, ...] = ()
    notes: list[str] = field(default_factory=list)


def check_options(options: DemoOptions) -> None:
    """Refuse bad input with one line (exit 2) before any process starts."""
    from models.feedback import LAW_NAMES
    from models.lmpc.controller import bundle_path

    if not sys.platform.startswith("linux"):
        raise ModelInputError("hil demo: the ipc bus between the processes is Linux only (docs/ipc_bus.md)")
    if options.law not in LAW_NAMES:
        raise ModelInputError(f"--law: unknown '{options.law}' (known: {', '.join(LAW_NAMES)})")
    if options.mode not in MODES:
        raise ModelInputError(f"--mode: unknown '{options.mode}' (known: {', '.join(MODES)})")
    manifest = bundle_path(options.robot, options.law, None) / "manifest.json"
    if not manifest.is_file():
        raise ModelInputError(f"{manifest}: no bundle for law '{options.law}' (export one with `hil pipeline`)")
    if options.duration_s is not None and not (math.isfinite(options.duration_s) and options.duration_s >= 0.05):
        raise ModelInputError(f"--duration: must be a finite number of seconds >= 0.05, got {options.duration_s!r}")
    if options.target_substeps < 1:
        raise ModelInputError(f"--target-substeps: must be >= 1, got {options.target_substeps}")


def demo_condition(options: DemoOptions, robot: Any) -> Any:
    """The paper's condition, cut to ``duration_s`` when given (its disturbance kept where it falls)."""
    from models.conditions import load_conditions

    conditions = load_conditions(None, robot=robot)
    for condition in conditions:
        if condition.name == options.condition:
            if options.duration_s is not None:
                condition = replace(condition, duration_s=float(options.duration_s))
                d = condition.disturbance
                if d is not None and d.time_s >= condition.duration_s:
                    condition = replace(condition, disturbance=None)  # the run ends before it
            return condition
    names = ", ".join(c.name for c in conditions)
    raise ModelInputError(f"--condition: unknown '{options.condition}' (the paper's: {names})")


# --- configs --------------------------------------------------------------------------------------


def target_config(options: DemoOptions, period_s: float, bus_dir: Path, control_socket: Path) -> dict[str, Any]:
    from sim_target.launch import CAN_FD

    return {
        "robot": options.robot,
        "period_s": period_s,
        "clock": "realtime" if options.realtime else "lockstep",
        "bus": {"interface": "ipc", "channel": str(bus_dir), **CAN_FD},
        "plant": {"substeps": options.target_substeps},
        "control_socket": str(control_socket),
    }


def runtime_config(
    options: DemoOptions,
    robot: Any,
    condition: Any,
    period_s: float,
    bus_dir: Path,
    conditions_file: Path,
    control_socket: Path,
    endpoint: str,
) -> dict[str, Any]:
    """``hil run``'s config: the shipped bundle, the condition from t = 0 on the placed arm, telemetry
    connecting to the demo's session, a control socket; lock-step (bus pacing) or real time (clock)."""
    from models.hil_experiment import runtime_config_dict
    from models.lmpc.controller import bundle_path
    from sim_target.launch import CAN_FD

    transport = {"interface": "ipc", "channel": str(bus_dir), **CAN_FD}
    data = runtime_config_dict(
        robot,
        bundle_path(robot.name, options.law, None),
        options.mode,
        transport,
        period_s,
        conditions_file,
        condition.name,
    )
    steps = round(condition.duration_s / period_s)
    data["loop"] = {
        "pacing": "clock" if options.realtime else "bus",
        "time_base": "wall" if options.realtime else "cycles",
        # The stats cover the whole run (not the default last 4096 cycles).
        "stats_window": min(steps + 20_000, 1 << 20),
        "stats_interval_s": 1.0,
        # A backstop only: the demo stops the daemon with SIGTERM when the run has covered the condition.
        "duration_s": condition.duration_s + 10.0,
    }
    data["telemetry"] = {"enabled": True, "listen": [], "connect": [endpoint], "stats_period_s": 1.0}
    data["control_socket"] = str(control_socket)
    return data


# --- the HIL run ----------------------------------------------------------------------------------


@contextlib.contextmanager
def _signals_blocked() -> Iterator[None]:
    """Hold SIGINT/SIGTERM while a child is being created and registered: a Ctrl-C then lands
    after the child is known, so the cleanup stops it (never a child nobody tracks)."""
    blocked = {signal.SIGINT, signal.SIGTERM}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, blocked)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


@contextlib.contextmanager
def _terminate_raises_interrupt() -> Iterator[None]:
    """SIGTERM to the demo (a CI timeout, ``kill``) takes the same path as Ctrl-C."""
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def _signals_ignored() -> Iterator[None]:
    """While the children are being stopped, a second Ctrl-C must not cut the stop short."""
    previous = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _open_listener(endpoint: str, robot: str) -> Any:
    """The demo's Zenoh peer session listening on ``endpoint`` (loopback), as a TelemetryClient."""
    import zenoh

    from hil_runtime.telemetry.config import zenoh_config
    from hil_runtime.telemetry.subscriber import TelemetryClient

    try:
        session = zenoh.open(zenoh_config("peer", [endpoint], [], None))
    except zenoh.ZError as exc:
        raise DemoError(f"cannot listen for telemetry on {endpoint}: {str(exc).splitlines()[0]}") from None
    return TelemetryClient(session, robot, timeout_s=3.0)


def run_hil(
    options: DemoOptions,
    robot: Any,
    condition: Any,
    on_phase: Callable[[DemoPhase], None],
    tick: Callable[[], None] | None = None,
) -> HilOutcome:
    """Start the target and the daemon, run the condition, stop everything; the run, in memory.

    ``on_phase`` is told of each phase; ``tick`` (the live view) is called every poll."""
    from hil_runtime.control import ControlError, send_command
    from hil_runtime.telemetry.cli import attach_watch
    from hil_runtime.telemetry.subscriber import TelemetryUnavailable
    from models.hil_experiment import conditions_yaml, run_start
    from sim_target.control import send_control

    period_s = 1e-3  # the paper's, and the shipped bundles'
    steps = round(condition.duration_s / period_s)
    phase = DemoPhase(duration_s=condition.duration_s, robot=robot.name)
    started = time.monotonic()
    wall: dict[str, float] = {}
    remove_stale_work_dirs()
    # A short private directory: Unix socket paths are limited to ~107 bytes.
    work = Path(tempfile.mkdtemp(prefix=WORK_PREFIX))
    (work / OWNER_FILE).write_text(str(os.getpid()))
    bus_dir, target_sock, runtime_sock = work / "bus", work / "target.sock", work / "runtime.sock"
    children: dict[str, Child] = {}
    processes: dict[str, Any] = {}
    client = None
    payloads: dict[str, list[bytes]] = {"state": [], "status": [], "events": [], "stats": []}
    fault: str | None = None
    documents: dict[str, Any] = {}
    schema = None
    shutdown: dict[str, Any] = {}
    logs: dict[str, str] = {}
    record: dict[str, np.ndarray] = {}

    def say(text: str) -> None:
        phase.text = text
        on_phase(phase)

    with _terminate_raises_interrupt():
        try:
            endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
            conditions_file = work / "conditions.yaml"
            conditions_file.write_text(conditions_yaml([condition]))
            (work / "target.yaml").write_text(yaml.safe_dump(target_config(options, period_s, bus_dir, target_sock)))
            (work / "runtime.yaml").write_text(
                yaml.safe_dump(
                    runtime_config(
                        options, robot, condition, period_s, bus_dir, conditions_file, runtime_sock, endpoint
                    )
                )
            )
            # Every check that needs no bus, here and now, before any process starts (one line, exit 2).
            from hil_runtime.daemon import check as check_runtime_config
            from sim_target.config import load_target_config

            load_target_config(work / "target.yaml")
            check_runtime_config(work / "runtime.yaml")
            # Listen first: the daemon connects at start-up, so no sample is published before the
            # demo's subscriptions exist.
            client = _open_listener(endpoint, robot.name)
            for key, sink in payloads.items():
                client.subscribe(key, sink.append)

            say("starting the pybullet target (hil target serve)")
            with _signals_blocked():
                children["target"] = Child(
                    "target", ["target", "serve", "--config", str(work / "target.yaml")], work / "target.log"
                )
            children["target"].wait_for_line("target serving", START_TIMEOUT_S)
            wall["target_start_s"] = time.monotonic() - started
            reply = send_control(target_sock, run_start(condition), timeout_s=10.0)
            if not reply.get("ok"):
                raise DemoError(f"the target refused the run start: {reply.get('error', 'no reason given')}")

            say("starting the runtime (hil run)")
            runtime_started = time.monotonic()
            with _signals_blocked():
                children["runtime"] = Child(
                    "runtime",
                    [
                        "run",
                        "--config",
                        str(work / "runtime.yaml"),
                        "--record",
                        str(work / "record.npz"),
                        "--record-cycles",
                        str(steps + 20_000),
                    ],
                    work / "runtime.log",
                )
            schema = _wait_for_schema(client, children["runtime"])
            phase.watch = attach_watch(client, schema)
            phase.joints = tuple(schema.joints)
            for name in ("config", "bundle"):
                with contextlib.suppress(TelemetryUnavailable):
                    documents[name] = client.query_json(name)

            active_at: float | None = None
            cycles, progressed_at = -1, time.monotonic()
            while True:
                now = time.monotonic()
                if not children["runtime"].alive():
                    raise DemoError(
                        f"hil run exited ({children['runtime'].process.returncode}) during the run: "
                        f"{children['runtime'].last_lines()}"
                    )
                try:
                    status = send_command(runtime_sock, "status", timeout_s=5.0)
                except ControlError:
                    status = {}
                state = status.get("state")
                if state == "ACTIVE" and active_at is None:
                    active_at = time.monotonic()
                    wall["runtime_start_s"] = active_at - runtime_started
                    say(f"running {options.law.upper()} {options.mode.upper()} on {condition.name}")
                if state == "FAULT":
                    fault = str(status.get("fault"))
                    say(f"FAULT: {fault}")
                    break
                if active_at is None and now - runtime_started > START_TIMEOUT_S:
                    raise DemoError(
                        f"hil run not ACTIVE within {START_TIMEOUT_S:g} s (state {state}): "
                        f"{children['runtime'].last_lines()}"
                    )
                if state == "ACTIVE":
                    if int(status.get("cycles") or 0) != cycles:
                        cycles, progressed_at = int(status.get("cycles") or 0), now
                    elif now - progressed_at > STALL_S:
                        raise DemoError(f"hil run: the loop made no progress for {STALL_S:g} s (cycle {cycles})")
                if active_at is not None:
                    if options.realtime:
                        phase.t_s = time.monotonic() - active_at
                    else:
                        phase.t_s = float(status.get("cycles") or 0) * period_s
                    if phase.t_s >= condition.duration_s + (0.05 if options.realtime else 0.0):
                        break
                if tick is not None:
                    tick()
                time.sleep(POLL_S)
            wall["run_s"] = time.monotonic() - (active_at or runtime_started)
        finally:
            # Everything below runs on success, Ctrl-C or error alike; a second Ctrl-C is ignored.
            with _signals_ignored():
                say("stopping: SIGTERM to hil run (quick stop), then the target")
                stop_started = time.monotonic()
                runtime = children.get("runtime")
                if runtime is not None:
                    processes["runtime"] = {
                        "pid": runtime.pid,
                        "exit_code": runtime.stop(STOP_TIMEOUT_S),
                        "stop_s": None if runtime.exit_s is None else round(runtime.exit_s, 3),
                    }
                    time.sleep(0.3)  # the daemon's last stats and status are on their way (it flushed them)
                if "target" in children and children["target"].alive():
                    with contextlib.suppress(OSError, ValueError):
                        after = send_control(target_sock, {"kind": "status"}, timeout_s=5.0)
                        enabled = [bool(x) for x in after.get("operation_enabled", [])]
                        shutdown["drives_operation_enabled_after_stop"] = enabled
                        shutdown["drives_stopped"] = bool(enabled) and not any(enabled)
                        shutdown["target_time_s"] = after.get("time_s")
                target = children.get("target")
                if target is not None:
                    processes["target"] = {
                        "pid": target.pid,
                        "exit_code": target.stop(TARGET_STOP_TIMEOUT_S),
                        "stop_s": None if target.exit_s is None else round(target.exit_s, 3),
                    }
                if client is not None:
                    with contextlib.suppress(Exception):
                        client.close()
                wall["stop_s"] = time.monotonic() - stop_started
                left = sorted(p.name for p in bus_dir.glob("*.sock")) if bus_dir.is_dir() else []
                shutdown["ipc_sockets_left"] = left
                shutdown["control_sockets_left"] = [p.name for p in (target_sock, runtime_sock) if p.exists()]
                shutdown["processes_alive"] = [name for name, c in children.items() if c.alive()]
                for name, child in children.items():
                    logs[name] = child.log_text()
                if (work / "record.npz").is_file():
                    with contextlib.suppress(OSError, ValueError), np.load(work / "record.npz") as data:
                        record = {k: data[k] for k in data.files}
                shutil.rmtree(work, ignore_errors=True)
                shutdown["work_dir_removed"] = not work.exists()
                say(_stop_line(processes, shutdown))
    shutdown["runtime_exit_code"] = processes.get("runtime", {}).get("exit_code")
    shutdown["target_exit_code"] = processes.get("target", {}).get("exit_code")
    if not record:
        raise DemoError(f"hil run wrote no record; its log: {_tail(logs.get('runtime', ''))}")
    return HilOutcome(
        record,
        schema,
        payloads["state"],
        payloads["status"],
        payloads["events"],
        payloads["stats"],
        documents,
        endpoint,
        fault,
        shutdown,
        processes,
        wall,
        logs,
        str(work),
        period_s,
    )


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


def _wait_for_schema(client: Any, runtime: Child) -> Any:
    """The runtime's telemetry schema, once its session is up (it configures the bus first)."""
    from hil_runtime.telemetry.codec import Schema
    from hil_runtime.telemetry.subscriber import TelemetryUnavailable

    end = time.monotonic() + START_TIMEOUT_S
    while True:
        if not runtime.alive():
            raise DemoError(f"hil run exited ({runtime.process.returncode}) at start-up: {runtime.last_lines()}")
        try:
            return Schema.from_json(client.query("schema", timeout_s=0.5))
        except TelemetryUnavailable:
            if time.monotonic() > end:
                raise DemoError(f"hil run: no telemetry within {START_TIMEOUT_S:g} s: {runtime.last_lines()}") from None


def _stop_line(processes: dict[str, Any], shutdown: dict[str, Any]) -> str:
    parts = []
    if "runtime" in processes:
        parts.append(f"hil run exit {processes['runtime']['exit_code']}")
    if "drives_stopped" in shutdown:
        parts.append(
            "drives stopped (Operation Enabled off)" if shutdown["drives_stopped"] else "drives NOT confirmed stopped"
        )
    if "target" in processes:
        parts.append(f"target exit {processes['target']['exit_code']}")
    leftovers = shutdown["processes_alive"] + shutdown["ipc_sockets_left"] + shutdown["control_sockets_left"]
    if shutdown["processes_alive"]:
        parts.append(f"processes still running: {', '.join(shutdown['processes_alive'])}")
    elif leftovers:
        parts.append(
            f"sockets a killed process left ({', '.join(leftovers)}): "
            + ("removed with the directory" if shutdown["work_dir_removed"] else "NOT removed")
        )
    else:
        parts.append(
            "no process, socket or directory left" if shutdown["work_dir_removed"] else "directory NOT removed"
        )
    return "stopped: " + ", ".join(parts)


def _tail(text: str, count: int = 3) -> str:
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return " | ".join(lines[-count:]) or "no output"


__all__ = ["BEST_LMPC_LAW", "DemoOptions", "DemoPhase", "HilOutcome", "check_options", "demo_condition", "run_hil"]
