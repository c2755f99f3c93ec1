"""The driver over the other transports: python-can-remote between two processes on loopback, and
SocketCAN vcan0 when this kernel has it (skipped with the reason otherwise)."""

from __future__ import annotations

import uuid
from collections.abc import Iterator

import can
import numpy as np
import pytest

from drivers.cia402.state_machine import State
from drivers.config import DriveBusConfig, parse_drive_bus_config
from drivers.drive_bus import DriveBus
from drivers.errors import FeedbackTimeoutError, TransportError
from drivers.transport import socketcan_unavailable
from sim_target.drives import EmulatedDrives, EmulatedDrivesConfig
from sim_target.testing.drive_process import DriveProcess, drive_process
from sim_target.testing.drive_rig import drive_bus_config
from sim_target.testing.fake_plant import FakePlant, lockstep


def _expected_position(torque_nm: np.ndarray, period_s: float, cycles: int, inertia: float = 0.5) -> np.ndarray:
    return period_s**2 * torque_nm / inertia * cycles * (cycles + 1) / 2


def _run_cycles(driver: DriveBus, period_s: float, cycles: int = 100) -> None:
    torque = np.array([1.0, -1.0, 2.0, -2.0, 0.5, 0.0])
    driver.enable()
    for _ in range(cycles):
        feedback = driver.exchange(torque)
    assert feedback.fresh.all()
    resolution = 1 / driver.counts_per_rad[0]
    np.testing.assert_allclose(feedback.position_rad, _expected_position(torque, period_s, cycles), atol=resolution)
    assert driver.quick_stop() == (State.QUICK_STOP_ACTIVE,) * 6
    counters = driver.counters
    assert counters.dropped == counters.late == counters.malformed == 0


def _connect_and_run(config: DriveBusConfig) -> DriveBus:
    """A driver on ``config``: connected, _run_cycles at 4 ms, closed."""
    driver = DriveBus(config)
    try:
        driver.connect()
        _run_cycles(driver, 0.004)
    finally:
        driver.close()
    return driver


@pytest.fixture
def target_process() -> Iterator[DriveProcess]:
    try:
        import can_remote  # noqa: F401
    except ImportError as exc:
        pytest.skip(f"python-can-remote is not installed: {exc}")
    with drive_process("--period-s", "0.004", "--channel", f"t-{uuid.uuid4().hex[:8]}") as target:
        yield target


@pytest.mark.parametrize("fd", [False, True], ids=["classical", "fd"])
def test_two_processes_over_the_loopback_bridge(target_process: DriveProcess, fd: bool) -> None:
    port = target_process.ready["port"]
    transport = {"interface": "remote", "bridge_host": "127.0.0.1", "bridge_port": port, "channel": ""}
    driver = _connect_and_run(drive_bus_config("unused", fd=fd, transport=transport, period_s=0.004))
    summary = target_process.finish()
    assert summary["syncs"] == driver.counters.cycles  # every SYNC crossed the process boundary
    assert target_process.proc.returncode == 0


def test_vcan0_when_the_kernel_has_it() -> None:
    reason = socketcan_unavailable("vcan0")
    if reason is not None:
        pytest.skip(f"vcan0 unavailable: {reason}")
    side = can.Bus(interface="socketcan", channel="vcan0", fd=True, ignore_config=True)
    drives = EmulatedDrives(side, EmulatedDrivesConfig(node_ids=tuple(range(1, 7))))
    plant = FakePlant(6, 0.004)
    lockstep(drives, plant)
    drives.start()
    config = parse_drive_bus_config(
        {
            "transport": {"interface": "socketcan", "channel": "vcan0"},
            "period_s": 0.004,
            "feedback_timeout_s": 0.5,
            "joints": [{"name": f"j{i}", "node_id": i + 1, "max_torque_nm": 150.0} for i in range(6)],
        }
    )
    try:
        _connect_and_run(config)
    finally:
        drives.close()
        side.shutdown()


def test_a_dead_bridge_peer_is_named_and_close_does_not_mask_it(
    target_process: DriveProcess,
) -> None:
    """The target process dies mid-run: the next exchange says the peer closed (not a feedback
    timeout), the drives' fail-safe cannot reach them, and close() raises nothing of its own."""
    port, proc = target_process.ready["port"], target_process.proc
    transport = {"interface": "remote", "bridge_host": "127.0.0.1", "bridge_port": port, "channel": ""}
    driver = DriveBus(drive_bus_config("unused", fd=True, transport=transport, period_s=0.004))
    try:
        driver.connect()
        driver.enable()
        for _ in range(20):
            driver.exchange(np.zeros(6))
        proc.kill()
        proc.wait(timeout=10)
        with pytest.raises(TransportError, match="^peer closed: the bridge at ws://127.0.0.1:") as info:
            for _ in range(1000):  # bounded: the first exchange after the kill normally raises
                driver.exchange(np.zeros(6))
        assert not isinstance(info.value, FeedbackTimeoutError)
        assert not driver.enabled
    finally:
        driver.close()  # the peer is gone: must neither raise nor hang
    driver.close()  # idempotent
