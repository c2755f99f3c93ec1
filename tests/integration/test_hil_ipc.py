"""The driver master and the pybullet target as two processes on the ipc bus (drivers/ipc):
lock-stepped at the paper's 1 ms period, the arm moves as the models simulator predicts, the deployed
config serves and leaves the bus directory clean, and a target that dies stops the driver."""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import pytest
import yaml

from drivers.drive_bus import DriveBus
from drivers.errors import FeedbackTimeoutError, HeartbeatLostError
from sim_target.testing.hil_target import drive_bus_config, serve_config, target_process
from tests.integration.test_hil_lockstep import SLOW_MACHINE, check_arm_across_processes, enabled_holding

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the ipc bus is Linux only")


def test_driver_moves_the_arm_across_processes_on_the_ipc_bus_at_1_ms(tmp_path: Path) -> None:
    period_s, cycles = 0.001, 400
    with target_process(tmp_path, period_s, substeps=32, transport="ipc") as target:
        assert target.ipc_dir is not None
        check_arm_across_processes(target, {"interface": "ipc", "channel": str(target.ipc_dir)}, period_s, cycles)
        code, err = target.stop()
        assert code == 0, err
        assert list(target.ipc_dir.iterdir()) == []  # both ends removed their sockets


def test_a_killed_target_stops_the_driver_with_a_feedback_error(tmp_path: Path) -> None:
    period_s = 0.001
    with target_process(tmp_path, period_s, substeps=8, transport="ipc") as target:
        bus = DriveBus(
            drive_bus_config(
                {"interface": "ipc", "channel": str(target.ipc_dir)},
                period_s,
                **{**SLOW_MACHINE, "feedback_timeout_s": 0.01},
            )
        )
        try:
            hold = enabled_holding(bus)
            target.process.send_signal(signal.SIGKILL)
            target.process.wait(10)
            with pytest.raises((FeedbackTimeoutError, HeartbeatLostError)):
                for _ in range(100):
                    bus.exchange(hold)
        finally:
            bus.close()


def test_serve_with_the_deployed_ipc_config_stops_cleanly_on_sigterm(tmp_path: Path) -> None:
    data = yaml.safe_load((Path(__file__).parents[2] / "deploy" / "target.ipc.yaml").read_text())
    assert data["bus"]["interface"] == "ipc" and data["period_s"] == 0.001
    data["control_socket"] = str(tmp_path / "target.sock")  # not the shared /tmp paths
    data["bus"]["channel"] = str(tmp_path / "bus")
    process, ready = serve_config(data, tmp_path / "target.ipc.yaml")
    assert f"target serving 6 drives on ipc:{tmp_path / 'bus'}" in ready, ready
    assert len(list((tmp_path / "bus").glob("*.sock"))) == 1
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=20)
    assert process.returncode == 0, err
    assert list((tmp_path / "bus").iterdir()) == []
