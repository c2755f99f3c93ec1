"""Driver + emulated drives + fake plant on one in-process virtual bus (shared by the drive-bus
tests and benchmarks/bench_can_exchange.py)."""

from __future__ import annotations

import shutil
import tempfile
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from drivers.config import DriveBusConfig, parse_drive_bus_config
from drivers.drive_bus import DriveBus
from sim_target.drives import EmulatedDrives, EmulatedDrivesConfig
from sim_target.testing.fake_plant import FakePlant, lockstep


def drive_bus_config(channel: str, n: int = 6, fd: bool = False, **overrides: Any) -> DriveBusConfig:
    transport: dict[str, Any] = {"interface": "virtual", "channel": channel}
    if fd:
        transport.update(fd=True, data_bitrate=5_000_000)
    data: dict[str, Any] = {
        "transport": transport,
        "period_s": 0.001 if fd else 0.004,
        "joints": [{"name": f"j{i}", "node_id": i + 1, "max_torque_nm": 150.0} for i in range(n)],
        # Generous: a loaded CI machine must not turn a slow cycle into a "lost" frame.
        "feedback_timeout_s": 0.5,
        "heartbeat_producer_ms": 20,
        "heartbeat_timeout_s": 0.5,
        # The drives stop on their own past this silence of the master: beyond the slowest cycle.
        "comm_loss_timeout_s": 2.0,
        # The fault tests count cycles against a budget of one tolerated miss (the default, 25,
        # rides out a loaded machine's stalls: docs/drivers.md).
        "max_missed_cycles": 1,
    }
    data.update(overrides)
    if "transport" in overrides:
        data["transport"] = {**transport, **overrides["transport"]}
    return parse_drive_bus_config(data, "test")


@dataclass
class Rig:
    config: DriveBusConfig
    driver: DriveBus
    drives: EmulatedDrives
    plant: FakePlant
    drive_side_bus: can.BusABC
    directory: Path | None = None  # the ipc bus's directory (removed on close)

    def close(self) -> None:
        self.driver.close()
        self.drives.close()
        self.drive_side_bus.shutdown()
        if self.directory is not None:
            shutil.rmtree(self.directory, ignore_errors=True)


def make_rig(
    n: int = 6,
    fd: bool = False,
    drive_ids: tuple[int, ...] | None = None,
    emulated: dict[str, Any] | None = None,
    connect: bool = True,
    interface: str = "virtual",
    **overrides: Any,
) -> Rig:
    """``interface``: "virtual" (python-can's, in-process) or "ipc" (the project's bus, in a
    temporary directory: the drives then take its raw datagram path)."""
    directory = None
    if interface == "ipc":
        directory = Path(tempfile.mkdtemp(prefix="rig-"))
        channel = str(directory / "bus")
        overrides["transport"] = {"interface": "ipc", "channel": channel, **overrides.get("transport", {})}
        side = can.Bus(interface="ipc", channel=channel, fd=fd)
    else:
        channel = f"drv-{uuid.uuid4().hex[:10]}"
        side = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    config = drive_bus_config(channel, n, fd, **overrides)
    drives = EmulatedDrives(
        side, EmulatedDrivesConfig(node_ids=drive_ids or tuple(range(1, n + 1)), **(emulated or {}))
    )
    plant = FakePlant(len(drives.config.node_ids), config.period_s)
    lockstep(drives, plant)
    drives.start()
    driver = DriveBus(config)
    rig = Rig(config, driver, drives, plant, side, directory)
    if connect:
        try:
            driver.connect()
        except BaseException:
            rig.close()
            raise
    return rig


def wait_until(condition: Callable[[], bool], timeout_s: float = 2.0) -> bool:
    """Poll ``condition`` (asynchronous counters); False after ``timeout_s`` instead of hanging."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.002)
    return condition()
