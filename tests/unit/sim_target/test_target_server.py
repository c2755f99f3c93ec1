"""The target server's clocks, fault routing, control socket and shutdown, against a recording
stand-in for the drive layer (the real drives are exercised in tests/integration)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from sim_target.config import DriveFault, FrameFault, parse_target_config
from sim_target.plant_protocol import JointState
from sim_target.server import TargetServer, make_plant, send_control

Q0 = [0.0, -0.5, 0.8, -0.3, 0.0, 0.0]
NO_RT_SETTINGS = {"fifo_priority": 0, "lock_memory": False}  # not for the pytest process


class RecordingDrives:
    def __init__(self) -> None:
        self.handler: Callable[[], None] | None = None
        self.torque_nm = np.zeros(6)
        self.enabled = np.ones(6, dtype=bool)
        self.published: list[JointState] = []
        self.faults: list[object] = []
        self.events: list[str] = []

    def set_sync_handler(self, handler: Callable[[], None]) -> None:
        self.handler = handler

    def sync(self) -> JointState:
        assert self.handler is not None
        self.handler()
        return self.published[-1]

    def commanded_torque_nm(self) -> np.ndarray:
        return self.torque_nm

    def serve_until(self, deadline_s: float, return_on_sync: bool = False) -> None:  # no bus: wait
        time.sleep(max(0.0, deadline_s - time.monotonic()))

    def operation_enabled(self) -> np.ndarray:
        return self.enabled

    def publish_feedback(self, state: JointState) -> None:
        self.published.append(state)

    def apply_fault(self, fault: object) -> None:
        self.faults.append(fault)

    def silence_heartbeat(self, node_id: int, silent: bool = True) -> None:
        self.events.append(f"heartbeat {node_id} {'silent' if silent else 'on'}")

    def safe_stop(self) -> None:
        self.events.append("safe_stop")

    def close(self) -> None:
        self.events.append("close")


def make_server(tmp_path: Path | None = None, **overrides: object) -> tuple[TargetServer, RecordingDrives]:
    data = {
        "plant": {"substeps": 4, "initial_position_rad": Q0},
        "bus": {"interface": "virtual", "channel": "unit", "fd": True, "data_bitrate": 5_000_000},
        **overrides,
    }
    config = parse_target_config(data)
    drives = RecordingDrives()
    return TargetServer(config, make_plant(config), drives), drives


def test_lockstep_each_sync_steps_exactly_one_period() -> None:
    server, drives = make_server()
    times = [drives.sync().time_s for _ in range(5)]
    assert times == pytest.approx([0.001, 0.002, 0.003, 0.004, 0.005], abs=1e-15)
    assert server.stats.steps == server.stats.syncs == 5
    server.shutdown()


def test_a_drive_not_enabled_is_braked_and_delivers_no_torque() -> None:
    server, drives = make_server()
    drives.enabled = np.array([True, True, False, True, True, True])
    drives.torque_nm = np.full(6, 3.0)
    for _ in range(200):
        state = drives.sync()
    assert state.position_rad[2] == pytest.approx(Q0[2], abs=1e-6)
    assert state.torque_nm[2] == 0.0 and state.torque_nm[0] == 3.0
    assert abs(state.position_rad[0] - Q0[0]) > 1e-3
    server.shutdown()


def test_lockstep_runs_are_deterministic() -> None:
    def run() -> np.ndarray:
        server, drives = make_server(plant={"substeps": 4, "initial_position_rad": Q0, "encoder_noise_rad": 1e-4})
        out = []
        for k in range(300):
            drives.torque_nm = 0.5 * np.sin(0.01 * k + np.arange(6))
            out.append(drives.sync().position_rad)
        server.shutdown()
        return np.array(out)

    np.testing.assert_array_equal(run(), run())


def test_scheduled_faults_reach_the_plant_and_the_drives_at_their_time() -> None:
    server, drives = make_server(
        faults=[
            {"kind": "payload", "at_s": 0.005, "mass_kg": 3.0},
            {"kind": "drive_fault", "at_s": 0.003, "node_id": 4, "error_code": 0x2310},
            {"kind": "frames", "at_s": 0.0, "drop_probability": 0.5},
            {"kind": "encoder_noise", "at_s": 0.004, "position_rad": 1e-3},
        ],
    )
    drives.enabled[:] = False
    drives.sync()
    assert [type(f) for f in drives.faults] == [FrameFault]
    for _ in range(3):
        drives.sync()
    assert isinstance(drives.faults[-1], DriveFault) and drives.faults[-1].node_id == 4
    # A fault due at t applies before the period starting at t: the state published for 4 ms is
    # clean, the one for 5 ms noisy; the payload (5 ms) arrives with the sixth SYNC.
    assert drives.published[-1].time_s == pytest.approx(0.004)
    assert np.abs(drives.published[-1].position_rad - np.array(Q0)).max() < 1e-6
    assert np.abs(drives.sync().position_rad - np.array(Q0)).max() > 1e-5
    assert server.plant.payload_kg == 0.0
    drives.sync()
    assert server.plant.payload_kg == 3.0
    server.shutdown()


def test_the_paper_impulse_kicks_the_arm_at_its_time() -> None:
    server, drives = make_server(faults=[{"kind": "impulse", "at_s": 0.010, "duration_s": 0.001}])
    # The arm held by gravity torques (models' dynamics): only the impulse can move it.
    from models.dynamics import make_dynamics
    from models.robots import load_robot

    dyn = make_dynamics(load_robot("ur5_paper"))
    for _ in range(10):
        drives.torque_nm = dyn.gravity(server.plant.state().position_rad)
        state = drives.sync()
    np.testing.assert_allclose(state.velocity_rad_s, 0.0, atol=1e-9)
    drives.torque_nm = dyn.gravity(server.plant.state().position_rad)
    state = drives.sync()
    assert np.abs(state.velocity_rad_s[5]) > 1.0  # 10 N·m for 1 ms on the light wrist
    server.shutdown()


def test_control_socket_injects_faults_and_reports_status(tmp_path: Path) -> None:
    sock = tmp_path / "target.sock"
    server, drives = make_server(control_socket=str(sock))
    server.serve_control(sock)
    assert send_control(sock, {"kind": "payload", "mass_kg": 1.5}) == {"ok": True}
    bad = send_control(sock, {"kind": "payload", "mass_kg": -1})
    assert bad["ok"] is False and "payload.mass_kg" in bad["error"]
    assert send_control(sock, {"kind": "drive_fault", "node_id": 2}) == {"ok": True}
    drives.sync()
    assert server.plant.payload_kg == 1.5
    assert isinstance(drives.faults[-1], DriveFault)
    status = send_control(sock, {"kind": "status"})
    assert status["ok"] and status["steps"] == 1 and status["payload_kg"] == 1.5
    server.shutdown()
    assert not sock.exists()


def test_realtime_clock_steps_on_its_own_and_stops_safely() -> None:
    server, drives = make_server(clock="realtime", period_s=0.002, realtime=NO_RT_SETTINGS)
    runner = threading.Thread(target=server.run)
    runner.start()
    while server.stats.steps < 5:
        threading.Event().wait(0.002)
    state = drives.sync()  # a SYNC answers with the latest state, it does not step
    assert drives.published[-1] is state
    server.stop()
    runner.join(timeout=10)
    assert not runner.is_alive()
    assert drives.events == ["safe_stop", "close"]
    assert server.stats.syncs == 1 and server.stats.steps >= 5


def test_lockstep_run_returns_on_stop_with_drives_safe() -> None:
    server, drives = make_server()
    runner = threading.Thread(target=server.run)
    runner.start()
    drives.sync()
    server.stop()
    runner.join(timeout=10)
    assert not runner.is_alive()
    assert drives.events == ["safe_stop", "close"]


def test_realtime_places_a_run_start_at_the_sync_that_finds_the_drives_enabled() -> None:
    from sim_target.config import RunStart

    server, drives = make_server(clock="realtime", realtime=NO_RT_SETTINGS)
    start = [0.1, -0.4, 0.7, -0.2, 0.1, 0.1]
    server.start_run(RunStart(kind="start", position_rad=tuple(start)))
    drives.enabled = np.array([True] * 5 + [False])
    assert drives.sync().time_s == 0.0 and server.stats.runs_started == 0  # not every drive enabled yet
    drives.enabled = np.ones(6, dtype=bool)
    state = drives.sync()  # the SYNC's answer carries the placed arm, not the pose before it
    np.testing.assert_allclose(state.position_rad, start, atol=1e-12)
    assert server.stats.runs_started == 1 and server.stats.steps == 0
    server.shutdown()
