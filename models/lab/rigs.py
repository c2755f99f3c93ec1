"""The rig a fault case runs on: the pybullet target, the runtime, a telemetry subscriber, a bus tap.

Two compositions (sim_target.launch has the target's side of both):

- :class:`InProcessRig`: the target (lock-step, python-can ``virtual`` channel, or the ipc bus with
  the target in its own process) and :class:`hil_runtime.runtime.Runtime` in this process, the
  loop on its own thread as ``hil run`` runs it; telemetry on (Zenoh on 127.0.0.1, a free port) with
  a subscriber collecting ``events`` and ``status``; on the virtual channel a tap receiving every
  RPDO the driver sends (the torque actually put on the bus).
- :class:`DaemonRig`: ``hil run`` as its own process against ``hil target serve`` on the ipc bus,
  with a Unix datagram socket as ``$NOTIFY_SOCKET`` (sd_notify: READY, STATUS, WATCHDOG,
  STOPPING) and the daemon's control socket.

The campaign's configs come from the lab's builders (models/lab/configs.py), its runtime from
:func:`hil_runtime.factory.build_runtime` (telemetry wired at construction).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from models.lab import configs
from models.lab.faults.observers import RpdoTap, TelemetryWatch
from models.lab.ports import free_loopback_port
from sim_target.testing.notify import NotifyListener
from sim_target.testing.ur5 import PD_BUNDLE, Q0_RAD, bus_joints

if TYPE_CHECKING:
    from sim_target.launch import Transport

PERIOD_S = 0.001
TARGET_SUBSTEPS = 8  # docs/target.md: parity 1.7e-3 rad over 2 s; faults need no more
# Driver timeouts of the campaign: tight enough that each protocol bound is what is measured
# (heartbeat, feedback), loose enough that a loaded 2-core machine does not trip them on its own.
FEEDBACK_TIMEOUT_S = 0.1
HEARTBEAT_PRODUCER_MS = 50
HEARTBEAT_TIMEOUT_S = 0.5
COMM_LOSS_TIMEOUT_S = 1.0
STATS_INTERVAL_S = 0.1


CAMPAIGN_DRIVER: dict[str, Any] = {
    "feedback_timeout_s": FEEDBACK_TIMEOUT_S,
    "heartbeat_producer_ms": HEARTBEAT_PRODUCER_MS,
    "heartbeat_timeout_s": HEARTBEAT_TIMEOUT_S,
    "sdo_timeout_s": 2.0,
    "state_change_timeout_s": 5.0,
    "comm_loss_timeout_s": COMM_LOSS_TIMEOUT_S,
}


def runtime_config_dict(
    transport: dict[str, Any],
    bundle: Path = PD_BUNDLE,
    telemetry_port: int | None = None,
    bus: dict[str, Any] | None = None,
    loop: dict[str, Any] | None = None,
    **sections: Any,
) -> dict[str, Any]:
    """The runtime's config for the campaign's target (the lab's builder): PD bundle (LMPC), hold,
    bus pacing. A ``telemetry`` section completes the campaign's own (controls, auth: the Zenoh cases)."""
    telemetry = sections.pop("telemetry", None) or {}
    return configs.runtime_config(
        "ur5_paper",
        bus_joints(),
        bundle,
        "lmpc",
        transport,
        PERIOD_S,
        driver={**CAMPAIGN_DRIVER, **(bus or {})},
        loop=configs.lockstep_loop(stats_interval_s=STATS_INTERVAL_S, warmup_cycles=50, **(loop or {})),
        telemetry=None
        if telemetry_port is None
        else configs.telemetry_section(STATS_INTERVAL_S, listen_port=telemetry_port, close_timeout_s=0.5, **telemetry),
        **sections,
    )


def target_config(q0_rad: tuple[float, ...] = Q0_RAD, **extra: Any) -> dict[str, Any]:
    """The campaign's target (the lab's builder): ur5_paper lock-stepped, starting at ``q0_rad``."""
    return configs.target_config("ur5_paper", PERIOD_S, TARGET_SUBSTEPS, initial_position_rad=q0_rad, **extra)


# --- in process -----------------------------------------------------------------------------------


@dataclass
class LoopThread:
    """The runtime's loop on its own thread, as ``hil run`` runs it (``daemon.serve``)."""

    runtime: Any
    thread: threading.Thread | None = None
    result: Any = None
    error: BaseException | None = None

    def start(self, max_cycles: int | None) -> None:
        def body() -> None:
            try:
                self.result = self.runtime.run(max_cycles=max_cycles)
            except BaseException as exc:  # noqa: BLE001 - reported as "daemon crashed"
                self.error = exc

        self.thread = threading.Thread(target=body, name="hil-loop", daemon=True)
        self.thread.start()

    @property
    def alive(self) -> bool:
        return self.thread is not None and self.thread.is_alive()

    def stop(self, timeout_s: float = 30.0) -> None:
        self.runtime.request_stop()
        if self.thread is not None:
            self.thread.join(timeout_s)


class InProcessRig:
    """Target + runtime + telemetry watch (+ RPDO tap on a virtual channel), one case's life."""

    def __init__(
        self,
        target: Any,
        config: Any,
        *,
        telemetry_port: int | None,
        record_cycles: int = 20_000,
        tap: bool = True,
        bundle: Any = None,
    ) -> None:
        from drivers.transport import open_bus
        from hil_runtime.factory import build_runtime, runtime_drive_bus

        self.target = target
        self.config = config
        # The campaign opens the python-can bus itself, so that a case can close it under the driver.
        self.can_bus = open_bus(config.bus.transport)
        self.drive_bus = runtime_drive_bus(config, self.can_bus)
        self.runtime = build_runtime(
            config, self.drive_bus, telemetry=telemetry_port is not None, record_cycles=record_cycles, bundle=bundle
        )
        self.telemetry_port = telemetry_port
        self.watch: TelemetryWatch | None = None
        self.tap: RpdoTap | None = None
        if tap and config.bus.transport.interface == "virtual":
            per_nm = np.array([node.permille_per_nm for node in self.drive_bus.nodes])
            self.tap = RpdoTap(config.bus.transport.channel, per_nm, self.runtime.limits.torque_limit_nm)
        self.loop = LoopThread(self.runtime)
        self.subscriber: subprocess.Popen[str] | None = None  # a second telemetry subscriber, when a case starts one
        self.cleanups: list[Callable[[], None]] = []  # a case's own helpers (rogue senders, busy processes)

    def start(self, watch: bool = True) -> None:
        """configure (bus up, telemetry up), the subscriber, activate."""
        self.runtime.configure()
        if watch and self.telemetry_port is not None:
            self.watch = TelemetryWatch(self.telemetry_port)

    def close(self) -> None:
        for cleanup in self.cleanups:
            with contextlib.suppress(Exception):
                cleanup()
        with contextlib.suppress(Exception):
            if self.loop.alive:
                self.loop.stop()
        with contextlib.suppress(Exception):
            self.runtime.shutdown()
        if self.watch is not None:
            self.watch.close()
        if self.tap is not None:
            self.tap.close()
        with contextlib.suppress(Exception):
            self.can_bus.shutdown()

    # what the target says about its drives and the arm
    def drive_states(self) -> list[str] | str:
        server = getattr(self.target, "server", None)
        if server is not None:
            return [state.value for state in server.drives.states()]
        try:
            status = self.target.status()
        except Exception:  # noqa: BLE001 - the target process is gone (a case killed it)
            return "target process gone"
        return ["operation enabled" if on else "not enabled" for on in status["operation_enabled"]]

    def arm_position(self) -> np.ndarray | None:
        server = getattr(self.target, "server", None)
        if server is not None:
            return np.asarray(server.plant.state().position_rad, float)
        try:
            return np.asarray(self.target.status()["position_rad"], float)
        except Exception:  # noqa: BLE001 - the target process is gone
            return None

    def position_limits(self) -> tuple[np.ndarray, np.ndarray]:
        limits = self.runtime.limits
        return limits.position_lower_rad, limits.position_upper_rad


@contextlib.contextmanager
def in_process_rig(
    transport: Transport = "virtual",
    *,
    telemetry: bool = True,
    q0_rad: tuple[float, ...] = Q0_RAD,
    bundle_path: Path = PD_BUNDLE,
    config_extra: dict[str, Any] | None = None,
    target_extra: dict[str, Any] | None = None,
    tap: bool = True,
) -> Iterator[InProcessRig]:
    from hil_runtime.config import parse_runtime_config
    from sim_target.launch import launch_target

    with launch_target(target_config(q0_rad, **(target_extra or {})), transport) as target:
        port = free_loopback_port() if telemetry else None
        data = runtime_config_dict(dict(target.transport), bundle_path, port, **(config_extra or {}))
        config = parse_runtime_config(data, "fault-campaign")
        rig = InProcessRig(target, config, telemetry_port=port, tap=tap)
        try:
            yield rig
        finally:
            rig.close()
            note_plant_lateness(target)


# --- hil run as its own process ---------------------------------------------------------------------


@dataclass
class DaemonRig:
    process: subprocess.Popen[str]
    control_socket: Path
    record: Path
    notify: NotifyListener
    telemetry_port: int
    target: Any
    stderr_lines: list[str] = field(default_factory=list)
    _reader: threading.Thread | None = None
    configured_at: float | None = None
    active_at: float | None = None  # when the daemon said it reached ACTIVE

    def start_reader(self) -> None:
        def read() -> None:
            assert self.process.stderr is not None
            for line in self.process.stderr:
                self.stderr_lines.append(line.rstrip("\n"))
                if self.configured_at is None and "hil run: configured" in line:
                    self.configured_at = time.monotonic()
                if self.active_at is None and "hil run: state ACTIVE" in line:
                    self.active_at = time.monotonic()

        self._reader = threading.Thread(target=read, name="daemon-stderr", daemon=True)
        self._reader.start()

    def status(self) -> dict[str, Any]:
        from hil_runtime.control import send_command

        return send_command(self.control_socket, "status")

    def wait_status(self, predicate: Any, timeout_s: float) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        last: dict[str, Any] = {}
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                return {"exited": self.process.returncode, **last}
            with contextlib.suppress(Exception):
                last = self.status()
                if predicate(last):
                    return last
            time.sleep(0.02)
        return {"timeout": True, **last}

    def wait_exit(self, timeout_s: float = 30.0) -> int:
        try:
            code = self.process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.process.kill()
            code = self.process.wait()
        if self._reader is not None:
            self._reader.join(timeout=5)
        return code


@contextlib.contextmanager
def daemon_rig(
    work: Path,
    *,
    watchdog_usec: int = 200_000,
    bus: dict[str, Any] | None = None,
    telemetry: bool = True,
    telemetry_lease_s: float | None = None,
) -> Iterator[DaemonRig]:
    """``hil target serve`` (ipc bus) and ``hil run`` as two processes, sd_notify to a socket of ours.
    ``telemetry_lease_s``: how long subscribers keep a silent runtime's link (a case that stops it)."""
    from sim_target.launch import launch_target
    from sim_target.testing.hil_target import start_hil_run

    (work / "t").mkdir(parents=True, exist_ok=True)
    with launch_target(target_config(), "ipc", work_dir=work / "t") as target:
        port = free_loopback_port()
        sock = work / "runtime.sock"
        data = runtime_config_dict(
            dict(target.transport), PD_BUNDLE, port if telemetry else None, bus=bus, control_socket=str(sock)
        )
        if telemetry and telemetry_lease_s is not None:
            data["telemetry"]["lease_s"] = telemetry_lease_s
        config_path = work / "runtime.yaml"
        config_path.write_text(yaml.safe_dump(data))
        notify = NotifyListener(work / "notify.sock")
        record = work / "run.npz"
        env = {**os.environ, "NOTIFY_SOCKET": str(notify.path), "WATCHDOG_USEC": str(watchdog_usec)}
        env.pop("WATCHDOG_PID", None)
        process = start_hil_run(config_path, record, env=env)
        rig = DaemonRig(process, sock, record, notify, port, target)
        rig.start_reader()
        try:
            yield rig
        finally:
            note_plant_lateness(target)
            if process.poll() is None:
                process.send_signal(signal.SIGCONT)
                process.send_signal(signal.SIGTERM)
                rig.wait_exit(30)
            notify.close()


# What each rig's target reported of its lateness (sim_target/lateness.py) when its case ended;
# campaign.run_case empties it before a case and marks the case invalid if its plant fell behind.
PLANT_LATENESS: list[tuple[dict[str, Any] | None, float]] = []


def note_plant_lateness(target: Any) -> None:
    """Keep the target's lateness over the case (None in lock-step); a target gone says nothing."""
    with contextlib.suppress(Exception):  # the case's own outcome matters more than this read
        status = target.status()
        PLANT_LATENESS.append((status.get("lateness"), float(status.get("period_s", PERIOD_S))))


def target_drives_enabled(target: Any) -> list[bool]:
    status = target.status()
    return [bool(x) for x in status["operation_enabled"]]


__all__ = [
    "DaemonRig",
    "InProcessRig",
    "LoopThread",
    "NotifyListener",
    "RpdoTap",
    "TelemetryWatch",
    "daemon_rig",
    "note_plant_lateness",
    "free_loopback_port",
    "in_process_rig",
    "runtime_config_dict",
    "target_config",
]
