"""The runtime (hil_runtime) drives the pybullet target (sim_target) through its CiA 402 drives.

(a) one process: runtime and target composed here on python-can's ``virtual`` bus, lock-stepped;
(b) two processes: ``hil target serve`` and ``hil run``, over the python-can-remote bridge on
127.0.0.1 and over the ipc bus; (c) SocketCAN vcan0 when it exists.

In each, the LMPC PD bundle ramps from the arm's pose onto condition C1, tracks it for 5 s with
every sample inside the limits (position, velocity, torque), and a stop (SIGTERM for the daemon)
leaves every drive quick-stopped, the brakes holding.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from drivers.drive_bus import DriveBus
from drivers.transport import socketcan_unavailable
from hil_runtime.config import parse_runtime_config
from hil_runtime.control import send_command
from hil_runtime.factory import build_runtime
from hil_runtime.lifecycle import LifecycleState
from hil_runtime.runtime import RunResult, Runtime
from sim_target.config import parse_fault
from sim_target.server import send_control
from sim_target.testing.hil_target import start_hil_run, target_in_process, target_process, unique_channel
from sim_target.testing.ur5 import MAX_TORQUE_NM, PD_BUNDLE, bus_joints

# Bounds on waits for frames on a loaded machine (not assertions on time): the lock-step target
# does not care about wall time.
SLOW_MACHINE = {
    "feedback_timeout_s": 0.2,
    "heartbeat_timeout_s": 1.0,
    "sdo_timeout_s": 2.0,
    "state_change_timeout_s": 5.0,
    "comm_loss_timeout_s": 1.0,
}
TRACK_S = 5.0
# What the PD bundle (LMPC) achieves on C1 in lock-step (pybullet, 32 substeps): max |q - q_ref| after
# the ramp, per joint, about 0.002-0.07 rad; bounded here with a margin, per joint.
TRACKING_BOUND_RAD = np.array([0.02, 0.05, 0.08, 0.1, 0.2, 0.05])


def runtime_config(transport: dict[str, Any], **sections: Any) -> dict[str, Any]:
    return {
        "robot": "ur5_paper",
        "bundle": {"path": str(PD_BUNDLE), "mode": "lmpc"},
        "bus": {
            "transport": {"fd": True, "data_bitrate": 5_000_000, **transport},
            "period_s": 0.001,
            "joints": bus_joints(),
            **SLOW_MACHINE,
        },
        "reference": {"kind": "condition", "condition": "C1", "ramp_s": 2.0},
        "loop": {"pacing": "bus"},
        **sections,
    }


def check_run(rec: dict[str, np.ndarray], ramp_cycles: int, limits: dict[str, Any]) -> None:
    """5 s on C1 after the ramp, every sample inside the limits, tracking as the bundle does."""
    n = rec["q"].shape[0]
    assert n >= ramp_cycles + int(TRACK_S / 0.001), f"only {n} rows, ramp {ramp_cycles}"
    position = np.asarray(limits["position_rad"])
    velocity = np.asarray(limits["velocity_rad_s"])
    assert np.all(np.abs(rec["q"]) <= position), "a sample left the position limits"
    assert np.all(np.abs(rec["qd"]) <= velocity), "a sample left the velocity limits"
    assert np.all(np.abs(rec["tau"]) <= np.asarray(MAX_TORQUE_NM) + 1e-9)
    np.testing.assert_allclose(np.diff(rec["t_s"]), 0.001, atol=1e-12)  # lock-step: no period skipped
    np.testing.assert_allclose(rec["q_ref"][0], rec["q"][0], atol=1e-12)  # the ramp starts where the arm is
    tracking = np.abs(rec["q"] - rec["q_ref"])[ramp_cycles:].max(axis=0)
    assert np.all(tracking < TRACKING_BOUND_RAD), f"tracking error {tracking}"
    moved = np.ptp(rec["q"][ramp_cycles:], axis=0)
    assert np.all(moved > 0.2), f"C1 moves every joint by >= pi/6: {moved}"


# --- (a) one process -------------------------------------------------------------------------------


def _track_c1(runtime: Runtime) -> RunResult:
    """configure, activate, the ramp and TRACK_S of C1: no fault, the record within the limits."""
    runtime.configure()
    assert runtime.activate()
    ramp = runtime.reference.ramp_cycles
    result = runtime.run(max_cycles=ramp + int(TRACK_S / 0.001))
    assert result.reason == "cycles" and result.fault is None
    check_run(runtime.record.arrays(), ramp, runtime.bundle.manifest.limits.model_dump())
    return result


def test_runtime_tracks_c1_with_the_target_in_one_process_then_stop_quick_stops() -> None:
    channel = unique_channel()
    config = parse_runtime_config(runtime_config({"interface": "virtual", "channel": channel}))
    with target_in_process(channel, 0.001) as target:
        runtime = build_runtime(config, record_cycles=10_000)
        try:
            result = _track_c1(runtime)
            assert isinstance(runtime.bus, DriveBus)  # the loop's JointBus protocol has no counters
            assert target.stats.steps == runtime.bus.counters.cycles  # lock-step: one step per SYNC
            stats = result.stats
            assert (stats["bus_dropped"], stats["bus_late"], stats["bus_malformed"], stats["overruns"]) == (0, 0, 0, 0)
            runtime.request_stop()  # what SIGTERM's handler does
            runtime.run(shutdown_at_end=True)
            assert runtime.state is LifecycleState.FINALIZED
            assert not target.drives.operation_enabled().any()  # every joint braked
            held = target.plant.state().position_rad
            time.sleep(0.05)
            np.testing.assert_allclose(target.plant.state().position_rad, held, atol=1e-9)
        finally:
            runtime.shutdown()


# --- (b) two processes: hil target serve + hil run -------------------------------------------------


def _wait_for(process: subprocess.Popen[str], socket: Path, cycles: int, timeout_s: float) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    status: dict[str, Any] = {}
    while time.monotonic() < deadline:
        if process.poll() is not None:
            err = process.stderr.read() if process.stderr else ""
            raise AssertionError(f"hil run exited {process.returncode}: {err}")
        if socket.exists():
            try:
                status = send_command(socket, "status")
            except Exception:  # noqa: BLE001 - starting up
                status = {}
            if status.get("state") == "FAULT":
                raise AssertionError(f"FAULT: {status.get('fault')}")
            if status.get("state") == "ACTIVE" and status["cycles"] >= status["ramp_cycles"] + cycles:
                return status
        time.sleep(0.1)
    raise AssertionError(f"not {cycles} cycles past the ramp in {timeout_s} s: {status}")


@pytest.mark.parametrize("transport", ["bridge", "ipc"])
def test_hil_run_and_hil_target_serve_as_two_processes(tmp_path: Path, transport: str) -> None:
    if transport == "ipc" and not sys.platform.startswith("linux"):
        pytest.skip("the ipc bus is Linux only")
    with target_process(tmp_path, 0.001, substeps=32, transport=transport) as target:
        bus = (
            {"interface": "remote", "channel": target.bridge_url}
            if transport == "bridge"
            else {"interface": "ipc", "channel": str(target.ipc_dir)}
        )
        sock = tmp_path / "runtime.sock"
        config_path = tmp_path / "runtime.yaml"
        config_path.write_text(yaml.safe_dump(runtime_config(bus, control_socket=str(sock))))
        record = tmp_path / "run.npz"
        process = start_hil_run(config_path, record)
        try:
            status = _wait_for(process, sock, int(TRACK_S / 0.001), timeout_s=240)
            assert status["fault"] is None and status["reference"] == "C1"
            sent = time.monotonic()
            process.send_signal(signal.SIGTERM)
            _, err = process.communicate(timeout=30)
            stop_s = time.monotonic() - sent
        finally:
            if process.poll() is None:
                process.kill()
                process.communicate()
        assert process.returncode == 0, err
        assert "state FINALIZED" in err and "Traceback" not in err
        after = send_control(target.control_socket, {"kind": "status"})
        assert after["operation_enabled"] == [False] * 6  # every drive quick-stopped, brakes on
        assert not sock.exists()
        with np.load(record) as data:
            rec = {k: data[k] for k in data.files}
        check_run(
            rec,
            status["ramp_cycles"],
            {
                "position_rad": [np.pi, 2.5132741228718345, 2.5132741228718345, np.pi, np.pi, np.pi],
                "velocity_rad_s": [2.5446900494077327] * 6,
            },
        )
        # SIGTERM to exit, process teardown included (the loop itself leaves within a cycle).
        assert stop_s < 5.0, f"{stop_s:.3f} s from SIGTERM to exit"
        code, target_err = target.stop()
    assert code == 0, target_err


# --- (c) SocketCAN -------------------------------------------------------------------------------------


def test_runtime_tracks_c1_over_vcan0() -> None:
    reason = socketcan_unavailable("vcan0")
    if reason is not None:
        pytest.skip(f"vcan0 unavailable: {reason}")
    config = parse_runtime_config(runtime_config({"interface": "socketcan", "channel": "vcan0"}))
    with target_in_process(
        "unused", 0.001, bus={"interface": "socketcan", "channel": "vcan0", "fd": True, "data_bitrate": 5_000_000}
    ) as target:
        runtime = build_runtime(config, record_cycles=10_000)
        try:
            _track_c1(runtime)
            runtime.request_stop()
            runtime.run(shutdown_at_end=True)
            assert not target.drives.operation_enabled().any()
        finally:
            runtime.shutdown()


# --- FAULT keeps the daemon up; hil reset clears it ---------------------------------------------------


def test_a_drive_fault_keeps_the_daemon_up_with_drives_stopped_until_hil_reset(tmp_path: Path) -> None:
    if not sys.platform.startswith("linux"):
        pytest.skip("the ipc bus is Linux only")
    with target_process(tmp_path, 0.001, substeps=8, transport="ipc") as target:
        sock = tmp_path / "runtime.sock"
        config_path = tmp_path / "runtime.yaml"
        config = runtime_config({"interface": "ipc", "channel": str(target.ipc_dir)}, control_socket=str(sock))
        config["reference"] = {"kind": "hold"}
        config_path.write_text(yaml.safe_dump(config))
        process = start_hil_run(config_path, tmp_path / "run.npz")
        try:
            _wait_for(process, sock, 200, timeout_s=120)
            assert send_control(target.control_socket, {"kind": "drive_fault", "node_id": 4, "error_code": 0x2310}) == {
                "ok": True
            }
            deadline = time.monotonic() + 30
            status = send_command(sock, "status")
            while status["state"] != "FAULT" and time.monotonic() < deadline:
                time.sleep(0.05)
                status = send_command(sock, "status")
            assert status["state"] == "FAULT" and status["fault"].startswith("drive_fault: drive 4"), status
            time.sleep(0.5)  # the daemon stays up, the drives stay stopped
            assert process.poll() is None
            assert send_command(sock, "status")["state"] == "FAULT"
            assert send_control(target.control_socket, {"kind": "status"})["operation_enabled"] == [False] * 6
            reset = subprocess.run(
                [sys.executable, "-m", "hil_runtime.cli", "reset", "--socket", str(sock)],
                capture_output=True,
                text=True,
                timeout=30,
                check=False,
            )
            assert reset.returncode == 0 and "state was FAULT" in reset.stdout, reset.stderr
            deadline = time.monotonic() + 30
            while send_command(sock, "status")["state"] != "ACTIVE" and time.monotonic() < deadline:
                time.sleep(0.05)
            status = send_command(sock, "status")
            assert status["state"] == "ACTIVE" and status["fault"] is None
            assert send_control(target.control_socket, {"kind": "status"})["operation_enabled"] == [True] * 6
            process.send_signal(signal.SIGTERM)
            _, err = process.communicate(timeout=30)
        finally:
            if process.poll() is None:
                process.kill()
                process.communicate()
        assert process.returncode == 0, err
        assert "state FAULT: drive_fault" in err and "state FINALIZED" in err
        assert send_control(target.control_socket, {"kind": "status"})["operation_enabled"] == [False] * 6


# --- faults injected at the target: FAULT within two cycles, drives stopped, reset brings it back --


@pytest.mark.parametrize(
    ("fault", "kind"),
    [
        # The driver's missed-TPDO budget and the supervisor's stale rule both allow one stale
        # cycle; whichever sees the second one first names the fault.
        ({"kind": "frames", "drop_probability": 1.0, "node_ids": [3]}, ("feedback_timeout", "stale_feedback")),
        ({"kind": "drive_fault", "node_id": 4, "error_code": 0x2310}, ("drive_fault",)),
    ],
    ids=["dropped-tpdos", "drive-fault"],
)
def test_an_injected_fault_is_a_fault_within_two_cycles_in_one_process(
    fault: dict[str, Any], kind: tuple[str, ...]
) -> None:
    channel = unique_channel()
    config = parse_runtime_config(
        runtime_config({"interface": "virtual", "channel": channel}, reference={"kind": "hold"})
    )
    with target_in_process(channel, 0.001, substeps=8) as target:
        runtime = build_runtime(config)
        try:
            runtime.configure()
            assert runtime.activate()
            assert runtime.run(max_cycles=50).fault is None
            injected_at = runtime.total_cycles
            target.inject(parse_fault(fault))  # applied at the next SYNC
            result = runtime.run(max_cycles=50, stop_on_fault=True)
            assert result.fault is not None and result.fault.startswith(kind), result.fault
            assert result.fault_cycle is not None and result.fault_cycle - injected_at <= 2
            assert not target.drives.operation_enabled().any()  # every drive stopped
            if kind == ("drive_fault",):  # the drive's fault is reset, the loop goes on from where the arm is
                target.inject(parse_fault({"kind": "frames", "drop_probability": 0.0}))
                runtime.request_reset()
                thread_result: dict[str, Any] = {}
                loop = threading.Thread(target=lambda: thread_result.setdefault("r", runtime.run(max_cycles=50)))
                loop.start()
                loop.join(30)
                assert thread_result["r"].reason == "cycles" and runtime.state is LifecycleState.ACTIVE
                assert target.drives.operation_enabled().all()
        finally:
            runtime.shutdown()
