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
run in their own sessions and die with the demo: models/lab/processes.py). docs/demo.md.

The options are models/demo/options.py, the two configs models/demo/configs.py.
"""

from __future__ import annotations

import contextlib
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from models.demo.configs import runtime_config, target_config
from models.demo.options import BEST_LMPC_LAW, DEFAULT_CONDITION, DemoOptions, check_options, demo_condition
from models.lab.configs import write_checked_configs
from models.lab.ports import free_loopback_port
from models.lab.processes import (
    OWNER_FILE,
    WORK_PREFIX,
    Child,
    DemoError,
    make_work_dir,
    remove_stale_work_dirs,
    signals_blocked,
    signals_ignored,
    terminate_raises_interrupt,
)

PERIOD_S = 1e-3  # the paper's, and the shipped bundles'
START_TIMEOUT_S = 180.0  # a fresh machine imports pybullet, onnxruntime, zenoh for the first time
STOP_TIMEOUT_S = 20.0  # SIGTERM -> exit; the quick stop waits at most the bus's state_change_timeout_s
TARGET_STOP_TIMEOUT_S = 10.0  # the target closes its bus and sockets in well under a second
STALL_S = 30.0  # ACTIVE without a cycle for this long: the rig is stuck (the drives stop on their own)
POLL_S = 0.1  # the control socket's status: progress, FAULT
RECORD_SPARE_CYCLES = 20_000  # room in the runtime's record for the hold cycles before the SIGTERM


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
    # The target's lateness over the run (sim_target/lateness.py; None in lock-step) and its
    # real-time settings, read from its status at the run's end.
    target_lateness: dict[str, Any] | None = None
    target_realtime: dict[str, Any] | None = None


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


def run_hil(
    options: DemoOptions,
    robot: Any,
    condition: Any,
    on_phase: Callable[[DemoPhase], None],
    tick: Callable[[], None] | None = None,
) -> HilOutcome:
    """Start the target and the daemon, run the condition, stop everything; the run, in memory.

    ``on_phase`` is told of each phase; ``tick`` (the live view) is called every poll."""
    run = _HilRun(options, robot, condition, on_phase, tick)
    with terminate_raises_interrupt():
        try:
            run.prepare()
            run.start_target()
            run.start_runtime()
            run.follow()
        finally:
            # Runs on success, Ctrl-C or error alike; a second Ctrl-C is ignored.
            with signals_ignored():
                run.stop()
    return run.outcome()


class _HilRun:
    """One HIL run: its private directory, its two children and what they leave behind."""

    def __init__(
        self,
        options: DemoOptions,
        robot: Any,
        condition: Any,
        on_phase: Callable[[DemoPhase], None],
        tick: Callable[[], None] | None,
    ) -> None:
        self.options, self.robot, self.condition = options, robot, condition
        self.on_phase, self.tick = on_phase, tick
        self.period_s = PERIOD_S
        self.steps = round(condition.duration_s / self.period_s)
        self.phase = DemoPhase(duration_s=condition.duration_s, robot=robot.name)
        self.started = time.monotonic()
        self.wall: dict[str, float] = {}
        self.work = make_work_dir()
        self.bus_dir = self.work / "bus"
        self.target_sock, self.runtime_sock = self.work / "target.sock", self.work / "runtime.sock"
        self.endpoint = ""
        self.children: dict[str, Child] = {}
        self.processes: dict[str, Any] = {}
        self.client: Any = None  # hil_runtime.telemetry.subscriber.TelemetryClient
        self.payloads: dict[str, list[bytes]] = {"state": [], "status": [], "events": [], "stats": []}
        self.fault: str | None = None
        self.target_lateness: dict[str, Any] | None = None
        self.target_realtime: dict[str, Any] | None = None
        self.documents: dict[str, Any] = {}
        self.schema: Any = None
        self.shutdown: dict[str, Any] = {}
        self.logs: dict[str, str] = {}
        self.record: dict[str, np.ndarray] = {}
        self.runtime_started = 0.0
        self.active_at: float | None = None
        self._progress = (-1, 0.0)  # (the last cycle count seen, when it changed): a stalled loop

    def say(self, text: str) -> None:
        self.phase.text = text
        self.on_phase(self.phase)

    # --- start ------------------------------------------------------------------------------------

    def prepare(self) -> None:
        """Write and check both configs (one line, exit 2, before any process starts); listen."""
        from models.hil_experiment.config import conditions_yaml

        work = self.work
        self.endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
        conditions_file = work / "conditions.yaml"
        conditions_file.write_text(conditions_yaml([self.condition]))
        target = target_config(self.options, self.period_s, self.bus_dir, self.target_sock)
        runtime = runtime_config(
            self.options,
            self.robot,
            self.condition,
            self.period_s,
            self.bus_dir,
            conditions_file,
            self.runtime_sock,
            self.endpoint,
        )
        write_checked_configs(work, target, runtime)
        # Listen first: the daemon connects at start-up, so no sample is published before the
        # demo's subscriptions exist.
        self.client = _open_listener(self.endpoint, self.robot.name)
        for key, sink in self.payloads.items():
            self.client.subscribe(key, sink.append)

    def start_target(self) -> None:
        """``hil target serve``, then the run start (the arm placed, the disturbance armed)."""
        from models.hil_experiment.config import run_start
        from sim_target.control import send_control

        self.say("starting the pybullet target (hil target serve)")
        with signals_blocked():
            self.children["target"] = Child(
                "target", ["target", "serve", "--config", str(self.work / "target.yaml")], self.work / "target.log"
            )
        self.children["target"].wait_for_line("target serving", START_TIMEOUT_S)
        self.wall["target_start_s"] = time.monotonic() - self.started
        reply = send_control(self.target_sock, run_start(self.condition), timeout_s=10.0)
        if not reply.get("ok"):
            raise DemoError(f"the target refused the run start: {reply.get('error', 'no reason given')}")

    def start_runtime(self) -> None:
        """``hil run``, recording; the live view attached once its telemetry schema is known."""
        from hil_runtime.telemetry.cli import attach_watch
        from hil_runtime.telemetry.subscriber import TelemetryUnavailable

        self.say("starting the runtime (hil run)")
        self.runtime_started = time.monotonic()
        args = ["run", "--config", str(self.work / "runtime.yaml"), "--record", str(self.work / "record.npz")]
        args += ["--record-cycles", str(self.steps + RECORD_SPARE_CYCLES)]
        with signals_blocked():
            self.children["runtime"] = Child("runtime", args, self.work / "runtime.log")
        self.schema = _wait_for_schema(self.client, self.children["runtime"])
        self.phase.watch = attach_watch(self.client, self.schema)
        self.phase.joints = tuple(self.schema.joints)
        for name in ("config", "bundle"):
            with contextlib.suppress(TelemetryUnavailable):
                self.documents[name] = self.client.query_json(name)

    # --- the run ----------------------------------------------------------------------------------

    def follow(self) -> None:
        """Poll the daemon's status until the run has covered the condition or FAULTed."""
        while not self._poll():
            if self.tick is not None:
                self.tick()
            time.sleep(POLL_S)
        self.wall["run_s"] = time.monotonic() - (self.active_at or self.runtime_started)
        self._read_target_lateness()

    def _read_target_lateness(self) -> None:
        """The target's lateness since the run start, before anything is stopped."""
        from sim_target.control import send_control

        with contextlib.suppress(OSError, ValueError):
            status = send_control(self.target_sock, {"kind": "status"}, timeout_s=5.0)
            self.target_lateness = status.get("lateness")
            self.target_realtime = status.get("realtime")

    def _poll(self) -> bool:
        """One look at the daemon; True when the run is over (covered, or FAULT)."""
        from hil_runtime.control import ControlError, send_command

        runtime = self.children["runtime"]
        now = time.monotonic()
        if not runtime.alive():
            raise DemoError(f"hil run exited ({runtime.process.returncode}) during the run: {runtime.last_lines()}")
        try:
            status = send_command(self.runtime_sock, "status", timeout_s=5.0)
        except ControlError:
            status = {}
        state = status.get("state")
        cycles = int(status.get("cycles") or 0)
        if state == "ACTIVE" and self.active_at is None:
            self.active_at = time.monotonic()
            self.wall["runtime_start_s"] = self.active_at - self.runtime_started
            self._progress = (cycles, now)
            options = self.options
            self.say(f"running {options.law.upper()} {options.mode.upper()} on {self.condition.name}")
        if state == "FAULT":
            self.fault = str(status.get("fault"))
            self.say(f"FAULT: {self.fault}")
            return True
        if self.active_at is None:
            if now - self.runtime_started > START_TIMEOUT_S:
                raise DemoError(
                    f"hil run not ACTIVE within {START_TIMEOUT_S:g} s (state {state}): {runtime.last_lines()}"
                )
            return False
        if state == "ACTIVE":
            seen, progressed_at = self._progress
            if cycles != seen:
                self._progress = (cycles, now)
            elif now - progressed_at > STALL_S:
                raise DemoError(f"hil run: the loop made no progress for {STALL_S:g} s (cycle {seen})")
        if self.options.realtime:
            self.phase.t_s = time.monotonic() - self.active_at
            return self.phase.t_s >= self.condition.duration_s + 0.05
        self.phase.t_s = cycles * self.period_s
        return self.phase.t_s >= self.condition.duration_s

    # --- stop -------------------------------------------------------------------------------------

    def stop(self) -> None:
        """The daemon first (SIGTERM: it quick-stops the drives), the drives checked at the target,
        the target, then what they left: sockets, the record, the private directory."""
        from sim_target.control import send_control

        self.say("stopping: SIGTERM to hil run (quick stop), then the target")
        stop_started = time.monotonic()
        if "runtime" in self.children:
            self._stop_child("runtime", STOP_TIMEOUT_S)
            time.sleep(0.3)  # the daemon's last stats and status are on their way (it flushed them)
        if "target" in self.children and self.children["target"].alive():
            with contextlib.suppress(OSError, ValueError):
                after = send_control(self.target_sock, {"kind": "status"}, timeout_s=5.0)
                enabled = [bool(x) for x in after.get("operation_enabled", [])]
                self.shutdown["drives_operation_enabled_after_stop"] = enabled
                self.shutdown["drives_stopped"] = bool(enabled) and not any(enabled)
                self.shutdown["target_time_s"] = after.get("time_s")
        if "target" in self.children:
            self._stop_child("target", TARGET_STOP_TIMEOUT_S)
        if self.client is not None:
            with contextlib.suppress(Exception):  # the session may be half open; closing is best effort
                self.client.close()
        self.wall["stop_s"] = time.monotonic() - stop_started
        self._collect_leftovers()
        self.say(_stop_line(self.processes, self.shutdown))

    def _stop_child(self, name: str, timeout_s: float) -> None:
        child = self.children[name]
        exit_code = child.stop(timeout_s)
        self.processes[name] = {
            "pid": child.pid,
            "exit_code": exit_code,
            "stop_s": None if child.exit_s is None else round(child.exit_s, 3),
        }

    def _collect_leftovers(self) -> None:
        """What the stopped children left: checked, the logs and the record read, the directory removed."""
        work, shutdown = self.work, self.shutdown
        shutdown["ipc_sockets_left"] = (
            sorted(p.name for p in self.bus_dir.glob("*.sock")) if self.bus_dir.is_dir() else []
        )
        shutdown["control_sockets_left"] = [p.name for p in (self.target_sock, self.runtime_sock) if p.exists()]
        shutdown["processes_alive"] = [name for name, c in self.children.items() if c.alive()]
        for name, child in self.children.items():
            self.logs[name] = child.log_text()
        if (work / "record.npz").is_file():
            with contextlib.suppress(OSError, ValueError), np.load(work / "record.npz") as data:
                self.record = {k: data[k] for k in data.files}
        shutil.rmtree(work, ignore_errors=True)
        shutdown["work_dir_removed"] = not work.exists()

    def outcome(self) -> HilOutcome:
        self.shutdown["runtime_exit_code"] = self.processes.get("runtime", {}).get("exit_code")
        self.shutdown["target_exit_code"] = self.processes.get("target", {}).get("exit_code")
        if not self.record:
            raise DemoError(f"hil run wrote no record; its log: {_tail(self.logs.get('runtime', ''))}")
        return HilOutcome(
            self.record,
            self.schema,
            self.payloads["state"],
            self.payloads["status"],
            self.payloads["events"],
            self.payloads["stats"],
            self.documents,
            self.endpoint,
            self.fault,
            self.shutdown,
            self.processes,
            self.wall,
            self.logs,
            str(self.work),
            self.period_s,
            self.target_lateness,
            self.target_realtime,
        )


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


# The options, the private directory's names and its sweep are also imported from here by
# models/cli/demo.py and the tests (this module was their home before the split).
__all__ = [
    "BEST_LMPC_LAW",
    "DEFAULT_CONDITION",
    "OWNER_FILE",
    "WORK_PREFIX",
    "DemoOptions",
    "DemoPhase",
    "HilOutcome",
    "check_options",
    "demo_condition",
    "remove_stale_work_dirs",
    "run_hil",
]
