"""Target configs checked against their URDF and the drive bus; faults checked completely before
'ok'; the control socket never deletes what it does not own (issue 9, items 4 and 7)."""

from __future__ import annotations

import logging
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.joint_bus import JointReadings
from sim_target.config import TargetConfigError, load_target_config, parse_target_config
from sim_target.server import TargetServer, build_server, make_plant, send_control

ROOT = Path(__file__).resolve().parents[3]
UR5_PAPER = ROOT / "models" / "robots" / "data" / "ur5_paper.urdf"
FD = "bus: {interface: virtual, channel: safety, fd: true, data_bitrate: 5000000}\n"
Q0 = [0.0, -0.5, 0.8, -0.3, 0.0, 0.0]


def _urdf(tmp_path: Path, old: str, new: str) -> Path:
    text = UR5_PAPER.read_text()
    assert old in text, old
    path = tmp_path / "arm.urdf"
    path.write_text(text.replace(old, new, 1))
    return path


def _first(tag: str) -> str:
    """The first occurrence of an element in ur5_paper.urdf, e.g. '<mass value="..."/>'."""
    text = UR5_PAPER.read_text()
    start = text.index(tag)
    return text[start : text.index("/>", start) + 2]


BAD_CONFIGS = [
    (
        FD + "plant: {initial_position_rad: [0, 0, 3.0, 0, 0, 0]}\n",
        "plant.initial_position_rad[2]: 3 rad is outside joint",
    ),
    (FD + "plant: {initial_position_rad: [0, 0, 0]}\n", "plant.initial_position_rad: 3 values for 6 joints"),
    (
        FD + "plant: {initial_position_rad: [.nan, 0, 0, 0, 0, 0]}\n",
        "plant.initial_position_rad.0: Input should be a finite number",
    ),
    (FD + "period_s: .nan\n", "period_s: Input should be a finite number"),
    ("period_s: 0.0002\nbus: {interface: virtual, fd: true, data_bitrate: 5000000}\n", "bus: 6 drives on CAN FD"),
    ("period_s: 0.002\nbus: {interface: virtual}\n", "bus: 6 drives on classical CAN at 1 Mbit/s"),
    ("period_s: 0.001\n", "above the 85% limit"),
    (FD + "drives: {node_ids: [1, 2, 3]}\n", "drives.node_ids: 3 ids for 6 joints"),
    (FD + "faults: [{kind: impulse, torque_nm: [1, 2]}]\n", "faults[0]: torque_nm: 2 values for 6 joints"),
    (FD + "faults: [{kind: drive_fault, node_id: 99}]\n", "faults[0]: node_id: node 99 is not a drive"),
    (FD + "faults: [{kind: heartbeat, node_id: 42}]\n", "faults[0]: node_id: node 42 is not a drive"),
    (FD + "faults: [{kind: frames, node_ids: [1, 9]}]\n", "faults[0]: node_ids[1]: node 9 is not a drive"),
    (FD + "faults: [{kind: impulse, duration_s: .inf}]\n", "duration_s: Input should be a finite number"),
    (FD + "faults: [{kind: payload, mass_kg: 1, inertia_kg_m2: [0.1, -0.1, 0.1]}]\n", "inertia_kg_m2.1"),
    ("", "empty file"),
    ("# only a comment\n", "empty file"),
    ("- a\n- list\n", "expected a mapping"),
]


@pytest.mark.parametrize(("text", "message"), BAD_CONFIGS)
def test_bad_target_configs_are_one_line_errors(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "target.yaml"
    path.write_text(text)
    with pytest.raises(TargetConfigError) as info:
        load_target_config(path)
    assert message in str(info.value) and str(path) in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (None, "mass", "<mass> value: negative"),
        (None, "ixx", "<inertia> ixx: negative"),
        (None, "limit", "<limit>: missing"),
    ],
)
def test_bad_urdfs_are_refused_before_pybullet(tmp_path: Path, old: str | None, new: str, message: str) -> None:
    if new == "mass":
        old = _first("<mass ")
        new = old.replace('value="', 'value="-')
    elif new == "ixx":
        old = _first("<inertia ")
        new = old.replace('ixx="', 'ixx="-')
    elif new == "limit":
        old, new = _first("<limit "), ""
    assert old is not None
    urdf = _urdf(tmp_path, old, new)
    path = tmp_path / "target.yaml"
    path.write_text(FD + f"urdf: {urdf.name}\n")
    with pytest.raises(TargetConfigError) as info:
        load_target_config(path)
    assert message in str(info.value) and "arm.urdf" in str(info.value) and str(path) in str(info.value)


@pytest.mark.parametrize("data", [bytes(range(256)), b"period_s: 0.001\x00\x00"])
def test_binary_files_are_refused(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "target.yaml"
    path.write_bytes(data)
    with pytest.raises(TargetConfigError, match="not a (UTF-8 )?text file"):
        load_target_config(path)


def test_shipped_rates_still_load_and_the_runtime_budget_is_used() -> None:
    load_target_config(ROOT / "deploy" / "target.virtual.yaml")
    parse_target_config({"period_s": 0.004, "bus": {"interface": "virtual"}})  # classical CAN, 250 Hz: fits


class StubDrives:
    def set_sync_handler(self, handler: Callable[[], None] | None) -> None:
        self.handler = handler

    def commanded_torque_nm(self) -> np.ndarray:
        return np.zeros(6)

    def serve_until(self, deadline_s: float, return_on_sync: bool = False) -> None:  # no bus: wait
        time.sleep(max(0.0, deadline_s - time.monotonic()))

    def operation_enabled(self) -> np.ndarray:
        return np.ones(6, bool)

    def publish_feedback(self, state: JointReadings) -> None:
        pass

    def apply_fault(self, fault: Any) -> None:
        pass

    def silence_heartbeat(self, node_id: int, silent: bool = True) -> None:
        pass

    def safe_stop(self) -> None:
        pass

    def close(self) -> None:
        pass


def _server(tmp_path: Path, **extra: object) -> TargetServer:
    bus = {"interface": "virtual", "channel": f"safety-{tmp_path.name}", "fd": True, "data_bitrate": 5_000_000}
    data = {"plant": {"substeps": 4, "initial_position_rad": Q0}, "bus": bus, **extra}
    config = parse_target_config(data)
    return TargetServer(config, make_plant(config), StubDrives())


@pytest.mark.parametrize(
    ("command", "message"),
    [
        ({"kind": "impulse", "torque_nm": [1, 2]}, "torque_nm: 2 values for 6 joints"),
        ({"kind": "payload", "mass_kg": 1, "inertia_kg_m2": [-1, 0, 0]}, "inertia_kg_m2"),
        ({"kind": "drive_fault", "node_id": 99}, "node 99 is not a drive"),
        ({"kind": "heartbeat", "node_id": 42}, "node 42 is not a drive"),
        ({"kind": "encoder_noise", "position_rad": float("inf")}, "finite"),
        ({"kind": "impulse", "duration_s": float("nan")}, "finite"),
    ],
)
def test_inject_refuses_before_ok_and_the_target_lives_on(tmp_path: Path, command: dict, message: str) -> None:
    sock = tmp_path / "t.sock"
    server = _server(tmp_path)
    server.serve_control(sock)
    try:
        reply = send_control(sock, command)
        assert reply["ok"] is False and message in reply["error"], reply
        drives = server.drives
        assert isinstance(drives, StubDrives) and drives.handler is not None
        drives.handler()  # a physics step after the refused fault: nothing pending fails
        assert send_control(sock, {"kind": "status"})["ok"] is True
    finally:
        server.shutdown()
    assert not sock.exists()


def test_start_up_says_scheduled_not_applied(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO, logger="sim_target.server"):
        server = _server(tmp_path, faults=[{"kind": "impulse", "at_s": 2.0}])
    server.shutdown()
    assert "fault scheduled at t=2.0000 s" in caplog.text and "applied" not in caplog.text


def test_a_regular_file_at_the_socket_path_is_refused_and_kept(tmp_path: Path) -> None:
    path = tmp_path / "precious.txt"
    path.write_text("not a socket")
    server = _server(tmp_path)
    try:
        with pytest.raises(TargetConfigError, match="exists and is not a socket; not removed"):
            server.serve_control(path)
    finally:
        server.shutdown()
    assert path.read_text() == "not a socket"


def test_a_second_target_refuses_a_socket_in_use_and_a_stale_one_is_reused(tmp_path: Path) -> None:
    sock = tmp_path / "t.sock"
    first, second = _server(tmp_path), _server(tmp_path)
    first.serve_control(sock)
    try:
        with pytest.raises(TargetConfigError, match="in use by another running target"):
            second.serve_control(sock)
        assert send_control(sock, {"kind": "status"})["ok"] is True  # the first one still serves
    finally:
        first.shutdown()
        second.shutdown()
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(sock))  # bound, never listening: what a killed run leaves behind
    stale.close()
    third = _server(tmp_path)
    try:
        third.serve_control(sock)
        assert send_control(sock, {"kind": "status"})["ok"] is True
    finally:
        third.shutdown()


def test_close_leaves_a_socket_that_replaced_ours(tmp_path: Path) -> None:
    sock = tmp_path / "t.sock"
    server = _server(tmp_path)
    server.serve_control(sock)
    sock.unlink()
    other = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    other.bind(str(sock))
    try:
        server.shutdown()
        assert sock.exists()  # not ours any more: not deleted
    finally:
        other.close()


def test_build_server_releases_everything_when_the_socket_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "in_the_way"
    path.mkdir()
    bus = {"interface": "virtual", "channel": "b", "fd": True, "data_bitrate": 5_000_000}
    config = parse_target_config({"plant": {"substeps": 4}, "control_socket": str(path), "bus": bus})
    with pytest.raises(TargetConfigError, match="not a socket"):
        build_server(config)
    assert path.is_dir()


def test_inject_client_imports_no_pybullet() -> None:
    code = (
        "import sys, sim_target.cli, sim_target.control, sim_target.config;"
        "sys.exit(1 if 'pybullet' in sys.modules else 0)"
    )
    assert subprocess.run([sys.executable, "-c", code], check=False, timeout=60).returncode == 0
