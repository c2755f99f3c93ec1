"""The driver master (drivers/drive_bus.py) runs the pybullet target (sim_target) lock-stepped:
each exchange's SYNC advances the arm by exactly one period.

(a) one process, python-can ``virtual`` bus; (b) two processes, the target as ``hil target serve``
with its bus served by the python-can-remote bridge on 127.0.0.1; (c) SocketCAN vcan0 when it
exists. The arm must move as the models simulator predicts for the torques the driver actually
sent; quick stop must engage the brakes. Faults injected through the target (its ``inject`` API or
control socket) must be reported by the driver within two cycles, counted in exchanges.

Every wait on the bus is bounded by the driver's own timeouts (generous here: the lock-step target
does not care about wall time, and these machines are shared), so nothing here asserts on timing.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import can
import numpy as np
import pytest

from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx
from drivers.cia402.state_machine import State
from drivers.drive_bus import DriveBus
from drivers.errors import DriveError, DriveFaultError, FeedbackTimeoutError, HeartbeatLostError
from drivers.transport import socketcan_unavailable
from models.conditions import Mismatch
from models.dynamics import make_dynamics
from models.robots import load_robot
from models.sim.closed_loop import ModelPlant, SimConfig
from sim_target.config import DriveFault, FrameFault, HeartbeatFault
from sim_target.server import send_control
from sim_target.testing.hil_target import (
    TargetProcess,
    drive_bus_config,
    serve_config,
    target_in_process,
    target_process,
    unique_channel,
)
from sim_target.testing.ur5 import MAX_TORQUE_NM, Q0_RAD

FREQUENCY_HZ = np.array([2.0, 2.2, 2.4, 2.6, 2.8, 3.0])
EXCURSION_RAD = 0.01  # sinusoid amplitude: M_ii(q0) (2 pi f)^2 x 10 mrad
LOOSE_TOLERANCE_RAD = 2e-3  # pybullet (semi-implicit Euler, substeps) vs RK4, plus encoder quantisation
# The lock-step target answers a SYNC after one physics step; these bound a cycle only if the
# machine stalls (they are limits to wait for frames, not assertions on time). The feedback timeout
# stays well below the heartbeat consumer's, so a silent drive is first missed by its TPDOs.
# The drives would quick-stop on their own when the master is silent for comm_loss_timeout_s;
# the checks below compute between exchanges with the drives enabled (seconds on a loaded
# machine), and a lock-stepped arm does not move without SYNCs anyway: not watched here.
# The fault tests count cycles against one tolerated miss (the default budget rides out stalls).
SLOW_MACHINE = {
    "feedback_timeout_s": 0.05,
    "heartbeat_timeout_s": 1.0,
    "sdo_timeout_s": 2.0,
    "state_change_timeout_s": 5.0,
    "comm_loss_timeout_s": None,
    "max_missed_cycles": 1,
}


def _gravity_plus_sinusoid() -> Callable[[int, np.ndarray, float], np.ndarray]:
    dynamics = make_dynamics(load_robot("ur5_paper"), backend="rne")
    amplitude = np.diag(dynamics.mass_matrix(np.array(Q0_RAD))) * (2 * np.pi * FREQUENCY_HZ) ** 2 * EXCURSION_RAD

    def torque_nm(k: int, q: np.ndarray, period_s: float) -> np.ndarray:
        return dynamics.gravity(q) + amplitude * np.sin(2 * np.pi * FREQUENCY_HZ * k * period_s)

    return torque_nm


def _models_replay(q0: np.ndarray, qd0: np.ndarray, commanded_nm: np.ndarray, period_s: float) -> np.ndarray:
    """The models simulator's plant (RK4, zero-order hold) driven by the torques that went on the bus."""
    sim = ModelPlant(load_robot("ur5_paper"), Mismatch(), SimConfig(period_s=period_s, substeps=4, plant_backend="rne"))
    q, qd = q0, qd0
    out = []
    for tau in commanded_nm:
        q, qd = sim.integrate(q, qd, tau, period_s)
        out.append(q)
    return np.array(out)


def _run_arm(bus: DriveBus, cycles: int, period_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """connect -> configure -> enable -> ``cycles`` exchanges: positions and velocities fed back,
    torques sent."""
    bus.connect()
    for node_id in bus.node_ids:  # the SDO configuration reached the drives
        assert bus.sdo_read_int(node_id, odx.MODES_DISPLAY) == odx.MODE_CYCLIC_SYNC_TORQUE
    assert bus.sdo_read_int(3, odx.RATED_TORQUE) == bus.config.joints[2].effective_rated_torque_mnm
    law = _gravity_plus_sinusoid()  # before enable: enabled drives quick-stop when the master idles
    bus.enable()
    assert bus.states == (State.OPERATION_ENABLED,) * 6
    q = np.array(Q0_RAD)
    positions, velocities, commanded = [], [], []
    for k in range(cycles):
        feedback = bus.exchange(law(k, q, period_s))
        assert feedback.fresh.all()
        np.testing.assert_allclose(feedback.torque_nm, feedback.commanded_torque_nm, atol=1e-9)
        q = feedback.position_rad
        positions.append(q)
        velocities.append(feedback.velocity_rad_s)
        commanded.append(feedback.commanded_torque_nm)
    return np.array(positions), np.array(velocities), np.array(commanded)


def _check_trajectory(positions: np.ndarray, velocities: np.ndarray, commanded: np.ndarray, period_s: float) -> None:
    assert np.ptp(positions, axis=0).min() > 5e-3, "every joint should really move"
    # enable() ends with one period in Operation Enabled at zero torque (the arm sags a little), so
    # the reference starts from the first cycle's feedback and replays the torques sent after it.
    reference = _models_replay(positions[0], velocities[0], commanded[1:], period_s)
    error = np.abs(positions[1:] - reference).max()
    assert error < LOOSE_TOLERANCE_RAD, f"HIL vs models simulator: max joint error {error:.2e} rad"


def _check_counters(bus: DriveBus, cycles: int) -> None:
    counters = bus.counters
    assert counters.cycles >= cycles
    assert (counters.dropped, counters.late, counters.malformed, counters.emcy) == (0, 0, 0, 0)


# --- (a) one process, virtual bus -----------------------------------------------------------------


def test_driver_moves_the_pybullet_arm_in_one_process_and_quick_stop_brakes() -> None:
    period_s, cycles = 0.001, 400
    channel = unique_channel()
    with target_in_process(channel, period_s) as target:
        bus = DriveBus(drive_bus_config({"interface": "virtual", "channel": channel}, period_s, **SLOW_MACHINE))
        try:
            positions, velocities, commanded = _run_arm(bus, cycles, period_s)
            _check_trajectory(positions, velocities, commanded, period_s)
            # Every exchange advanced the target by exactly one period (lock-step).
            assert target.stats.steps == bus.counters.cycles
            np.testing.assert_allclose(target.plant.state().position_rad, positions[-1], atol=1e-5)

            states = bus.quick_stop()
            assert set(states) <= {State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED}
            assert not target.drives.operation_enabled().any()  # every joint braked
            held = target.plant.state().position_rad
            steps = target.stats.steps
            assert set(bus.disable()) == {State.SWITCH_ON_DISABLED}
            assert target.stats.steps > steps  # the disable cycles stepped the plant...
            state = target.plant.state()
            np.testing.assert_allclose(state.position_rad, held, atol=1e-4)  # ...and the brakes held
            np.testing.assert_allclose(state.velocity_rad_s, 0.0, atol=1e-3)
            _check_counters(bus, cycles)
        finally:
            bus.close()
    assert not bus.enabled


# --- (b) two processes over the loopback bridge -----------------------------------------------------


def enabled_holding(bus: DriveBus) -> np.ndarray:
    """Connect and enable ``bus``; three exchanges at zero torque, each with every drive fresh."""
    bus.connect()
    bus.enable()
    hold = np.zeros(6)
    for _ in range(3):
        assert bus.exchange(hold).fresh.all()
    return hold


def check_arm_across_processes(target: TargetProcess, transport: dict[str, str], period_s: float, cycles: int) -> None:
    """The driver moves the arm of a ``hil target serve`` process lock-stepped, then brakes it."""
    bus = DriveBus(drive_bus_config(transport, period_s, **SLOW_MACHINE))
    try:
        positions, velocities, commanded = _run_arm(bus, cycles, period_s)
        _check_trajectory(positions, velocities, commanded, period_s)
        status = send_control(target.control_socket, {"kind": "status"})
        assert status["steps"] == bus.counters.cycles  # lock-stepped across the processes
        np.testing.assert_allclose(status["position_rad"], positions[-1], atol=1e-5)

        bus.quick_stop()
        status = send_control(target.control_socket, {"kind": "status"})
        assert status["operation_enabled"] == [False] * 6
        assert set(bus.disable()) == {State.SWITCH_ON_DISABLED}
        after = send_control(target.control_socket, {"kind": "status"})
        assert after["steps"] > status["steps"]
        np.testing.assert_allclose(after["position_rad"], status["position_rad"], atol=1e-4)  # braked
        _check_counters(bus, cycles)
    finally:
        bus.close()


def test_driver_moves_the_arm_across_processes_over_the_loopback_bridge(tmp_path: Path) -> None:
    period_s, cycles = 0.002, 300
    with target_process(tmp_path, period_s, substeps=32) as target:
        check_arm_across_processes(target, {"interface": "remote", "channel": target.bridge_url}, period_s, cycles)
        code, err = target.stop()
    assert code == 0, err
    assert "target stopped after" in err
    assert not target.control_socket.exists()


# --- (c) SocketCAN vcan0 ----------------------------------------------------------------------------


def test_driver_moves_the_arm_over_vcan0() -> None:
    reason = socketcan_unavailable("vcan0")
    if reason is not None:
        pytest.skip(f"vcan0 unavailable: {reason}")
    period_s, cycles = 0.001, 200
    transport = {"interface": "socketcan", "channel": "vcan0"}
    with target_in_process(
        "unused", period_s, bus={"interface": "socketcan", "channel": "vcan0", "fd": True, "data_bitrate": 5_000_000}
    ):
        bus = DriveBus(drive_bus_config(transport, period_s, **SLOW_MACHINE))
        try:
            positions, velocities, commanded = _run_arm(bus, cycles, period_s)
            _check_trajectory(positions, velocities, commanded, period_s)
        finally:
            bus.close()


# --- faults, counted in cycles ------------------------------------------------------------------------


def _cycles_until_error(bus: DriveBus, torque: np.ndarray, limit: int = 20) -> tuple[int, DriveError]:
    for k in range(1, limit + 1):
        try:
            bus.exchange(torque)
        except DriveError as exc:
            return k, exc
    raise AssertionError(f"no fault reported in {limit} cycles")


def _enabled_bus(channel: str, period_s: float, **extra: object) -> tuple[DriveBus, np.ndarray]:
    bus = DriveBus(
        drive_bus_config({"interface": "virtual", "channel": channel}, period_s, **{**SLOW_MACHINE, **extra})
    )
    bus.connect()
    bus.enable()
    hold = make_dynamics(load_robot("ur5_paper"), backend="rne").gravity(np.array(Q0_RAD))
    for _ in range(5):  # healthy first: nothing is reported before the fault
        assert bus.exchange(hold).fresh.all()
    return bus, hold


@pytest.mark.parametrize(
    ("fault", "error_type"),
    [
        (FrameFault(kind="frames", drop_probability=1.0, node_ids=(3,)), FeedbackTimeoutError),
        (DriveFault(kind="drive_fault", node_id=4, error_code=0x2310), DriveFaultError),
    ],
    ids=["dropped-tpdos", "drive-fault"],
)
def test_injected_fault_is_reported_within_two_cycles(fault: FrameFault | DriveFault, error_type: type) -> None:
    period_s = 0.001
    channel = unique_channel()
    with target_in_process(channel, period_s) as target:
        bus, hold = _enabled_bus(channel, period_s)
        try:
            target.inject(fault)  # applied at the next SYNC
            cycles, error = _cycles_until_error(bus, hold)
            assert isinstance(error, error_type), repr(error)
            assert cycles <= 2, f"{error!r} reported after {cycles} cycles"
            if isinstance(error, FeedbackTimeoutError):
                assert error.node_ids == (3,)
                assert bus.counters.dropped >= 2
            else:
                assert isinstance(error, DriveFaultError)
                assert (error.node_id, error.code) == (4, 0x2310)
                assert bus.counters.emcy == 1
                assert not bus.enabled
        finally:
            bus.close()


def test_heartbeat_loss_is_reported_within_two_cycles_of_its_timeout() -> None:
    """The heartbeat consumer deadline is wall time (CiA 301): the loop runs paced at 50 Hz, an
    observer on the bus notes the last heartbeat, and the driver must report the loss by the
    second cycle that starts after that heartbeat plus the consumer timeout."""
    period_s, timeout_s = 0.02, 0.1
    channel = unique_channel()
    last_seen = {"t": 0.0}
    stop = threading.Event()
    observer = can.Bus(interface="virtual", channel=channel, protocol=can.CanProtocol.CAN_FD)

    def watch() -> None:
        while not stop.is_set():
            msg = observer.recv(0.01)
            if msg is not None and msg.arbitration_id == fr.HEARTBEAT_BASE + 5:
                last_seen["t"] = time.monotonic()

    watcher = threading.Thread(target=watch, daemon=True)
    with target_in_process(channel, period_s) as target:
        bus, hold = _enabled_bus(channel, period_s, heartbeat_producer_ms=20, heartbeat_timeout_s=timeout_s)
        watcher.start()
        try:
            target.inject(HeartbeatFault(kind="heartbeat", node_id=5))
            starts: list[float] = []
            error: DriveError | None = None
            next_s = time.monotonic()
            for _ in range(50):
                next_s += period_s
                time.sleep(max(0.0, next_s - time.monotonic()))
                starts.append(time.monotonic())
                try:
                    feedback = bus.exchange(hold)
                except DriveError as exc:
                    error = exc
                    break
                assert feedback.fresh.all()  # PDOs go on: only the heartbeat stopped
            assert isinstance(error, HeartbeatLostError), repr(error)
            assert error.node_id == 5
            deadline = last_seen["t"] + timeout_s
            after_deadline = sum(1 for s in starts if s > deadline)
            assert after_deadline <= 2, f"reported {after_deadline} cycles after the heartbeat deadline"
            assert len(starts) > 2  # not before the consumer time could have run out
        finally:
            stop.set()
            watcher.join(timeout=2)
            observer.shutdown()
            bus.close()


@pytest.mark.parametrize(
    ("command", "error_type"),
    [
        ({"kind": "frames", "drop_probability": 1.0, "node_ids": [2]}, FeedbackTimeoutError),
        ({"kind": "drive_fault", "node_id": 6, "error_code": 0x4310}, DriveFaultError),
    ],
    ids=["dropped-tpdos", "drive-fault"],
)
def test_fault_injected_through_the_control_socket_across_processes(
    tmp_path: Path, command: dict, error_type: type
) -> None:
    period_s = 0.002
    with target_process(tmp_path, period_s, substeps=8) as target:
        bus = DriveBus(
            drive_bus_config({"interface": "remote", "channel": target.bridge_url}, period_s, **SLOW_MACHINE)
        )
        try:
            hold = enabled_holding(bus)
            assert send_control(target.control_socket, command) == {"ok": True}
            cycles, error = _cycles_until_error(bus, hold)
            assert isinstance(error, error_type), repr(error)
            assert cycles <= 2, f"{error!r} reported after {cycles} cycles"
            node = command["node_id"] if "node_id" in command else command["node_ids"][0]
            assert getattr(error, "node_id", None) == node or getattr(error, "node_ids", None) == (node,)
        finally:
            bus.close()
        code, err = target.stop()
    assert code == 0, err


def test_max_torque_is_the_urdf_effort_limit() -> None:
    """The joints' configured max torque is the target arm's own effort limit."""
    from sim_target.plant import PybulletPlant

    with PybulletPlant(period_s=0.001) as plant:
        np.testing.assert_allclose(plant.torque_limit_nm, MAX_TORQUE_NM)


def test_serve_with_the_deployed_virtual_config_stops_cleanly_on_sigterm(tmp_path: Path) -> None:
    import signal

    import yaml

    data = yaml.safe_load((Path(__file__).parents[2] / "deploy" / "target.virtual.yaml").read_text())
    data["control_socket"] = str(tmp_path / "target.sock")  # not the shared /tmp path
    process, ready = serve_config(data, tmp_path / "target.virtual.yaml")
    assert "target serving 6 drives on virtual:hil" in ready, ready
    assert send_control(tmp_path / "target.sock", {"kind": "status"})["ok"]
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=20)
    assert process.returncode == 0, err
    assert "target stopped after 0 steps" in err
    assert not (tmp_path / "target.sock").exists()
