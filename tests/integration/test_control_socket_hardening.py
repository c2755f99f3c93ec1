"""The control sockets (runtime and target) under hostile clients (issue 20): a line nested
100,000 deep, thousands of idle connections, a daemon that refuses; and the target's limits on
what a command may ask (a 1e30 N·m impulse, a start faster than the joints can move)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from drivers.json_socket import MAX_CLIENTS, JsonLineServer, json_depth, request_json_line
from hil_runtime.control import ControlError, ControlServer, send_command
from sim_target.config import (
    TargetConfigError,
    check_fault,
    check_run_start,
    load_target_config,
    parse_fault,
    parse_run_start,
    target_layout,
)
from sim_target.control import ControlServer as TargetControlServer

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


class FakeRuntime:
    def __init__(self) -> None:
        self.stops = 0

    def status(self) -> dict[str, Any]:
        return {"state": "ACTIVE", "fault": None}

    def request_stop(self) -> None:
        self.stops += 1

    def request_reset(self) -> None:
        pass

    def request_activate(self) -> None:
        pass


class FakeTarget:
    def status(self) -> dict[str, Any]:
        return {"running": True}

    def start_run(self, start: object) -> None:
        pass

    def inject(self, fault: object) -> None:
        pass


def _raw_request(path: Path, line: bytes, timeout_s: float = 5.0) -> dict[str, Any]:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        sock.connect(str(path))
        sock.sendall(line + b"\n")
        data = b""
        while not data.endswith(b"\n"):
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
    reply: dict[str, Any] = json.loads(data)
    return reply


@pytest.mark.parametrize("side", ["runtime", "target"])
@pytest.mark.parametrize("depth", [100_000, 5_000])
def test_a_deeply_nested_line_gets_an_error_reply_and_no_traceback(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], side: str, depth: int
) -> None:
    path = tmp_path / "c.sock"
    server = ControlServer(path, FakeRuntime()) if side == "runtime" else TargetControlServer(path, FakeTarget())
    try:
        reply = _raw_request(path, b"[" * depth + b"]" * depth)
        assert reply["ok"] is False and ("nested" in reply["error"] or "bytes" in reply["error"])
        # the server still answers
        good = b'{"command": "status"}' if side == "runtime" else b'{"kind": "status"}'
        assert _raw_request(path, good)["ok"] is True
    finally:
        server.close()
    assert "Traceback" not in capfd.readouterr().err


def test_json_depth_skips_strings() -> None:
    assert json_depth('{"a": [1, {"b": "[[[[{{{"}]}') == 3
    assert json_depth("[" * 40 + "]" * 40) == 40


def test_idle_clients_are_bounded_and_cost_no_thread(tmp_path: Path) -> None:
    path = tmp_path / "c.sock"
    runtime = FakeRuntime()
    server = ControlServer(path, runtime)
    threads_before = threading.active_count()
    idle = []
    try:
        for _ in range(300):
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            sock.connect(str(path))
            idle.append(sock)
        time.sleep(0.3)
        assert threading.active_count() == threads_before  # one server thread, whatever the clients
        # the oldest idlers were told so and closed to make room; a command still gets through
        oldest = idle[0]
        oldest.settimeout(2.0)
        assert b"too many clients" in oldest.recv(4096)
        assert send_command(path, "stop")["ok"] is True and runtime.stops == 1
        assert server._server.client_count <= MAX_CLIENTS
    finally:
        for sock in idle:
            sock.close()
        server.close()
    assert MAX_CLIENTS < 300


def test_an_idle_client_is_timed_out(tmp_path: Path) -> None:
    server = JsonLineServer(
        tmp_path / "c.sock", lambda line: {"ok": True}, in_use_by="x", thread_name="t", idle_timeout_s=0.2
    )
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.connect(str(tmp_path / "c.sock"))
            sock.settimeout(3.0)
            started = time.monotonic()
            assert sock.recv(10) == b""  # closed by the server
            assert time.monotonic() - started < 2.0
        assert server.timed_out == 1
    finally:
        server.close()


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs to keep one free")
def test_the_control_thread_stays_off_the_loop_cpus(tmp_path: Path) -> None:
    loop_cpu = min(os.sched_getaffinity(0))
    server = ControlServer(tmp_path / "c.sock", FakeRuntime(), avoid_cpus=(loop_cpu,))
    try:
        send_command(tmp_path / "c.sock", "status")  # the thread has started and pinned itself
        thread = server._server._thread
        assert thread.native_id is not None
        assert loop_cpu not in os.sched_getaffinity(thread.native_id)
    finally:
        server.close()


def _refusing_server(path: Path) -> JsonLineServer:
    return JsonLineServer(
        path, lambda line: {"ok": False, "error": "not now: FAULT"}, in_use_by="x", thread_name="refusing"
    )


def test_a_refusal_is_an_error_not_a_success(tmp_path: Path) -> None:
    server = _refusing_server(tmp_path / "c.sock")
    try:
        with pytest.raises(ControlError, match="stop refused: not now: FAULT"):
            send_command(tmp_path / "c.sock", "stop")
    finally:
        server.close()


@pytest.mark.parametrize("command", ["status", "stop", "reset"])
def test_hil_control_commands_exit_2_on_a_refusal(tmp_path: Path, hil_command: list[str], command: str) -> None:
    server = _refusing_server(tmp_path / "c.sock")
    try:
        done = subprocess.run(
            [*hil_command, command, "--socket", str(tmp_path / "c.sock")], capture_output=True, text=True, timeout=60
        )
    finally:
        server.close()
    assert done.returncode == 2, done.stdout + done.stderr
    assert "not now: FAULT" in done.stderr and "Traceback" not in done.stderr
    assert "requested" not in done.stdout


def test_request_json_line_still_works_for_the_owner(tmp_path: Path) -> None:
    server = _refusing_server(tmp_path / "c.sock")
    try:
        assert request_json_line(tmp_path / "c.sock", {"a": 1}, 2.0)["ok"] is False
    finally:
        server.close()


# --- what a target command may ask ---------------------------------------------------------------


def _layout() -> Any:
    return target_layout(load_target_config(DEPLOY / "target.virtual.yaml"))


def test_the_target_refuses_an_impulse_of_1e30_nm() -> None:
    layout = _layout()
    check_fault(parse_fault({"kind": "impulse"}), layout)  # the paper's disturbance is fine
    fault = parse_fault({"kind": "impulse", "torque_nm": [1e30, 0, 0, 0, 0, 0]})
    with pytest.raises(TargetConfigError, match=r"torque_nm\[0\]: 1e\+30 N·m is beyond"):
        check_fault(fault, layout, "control")


def test_the_target_refuses_a_start_velocity_beyond_the_limits() -> None:
    layout = _layout()
    position = [0.0, -0.5, 0.8, -0.3, 0.0, 0.0]
    check_run_start(parse_run_start({"kind": "start", "position_rad": position, "velocity_rad_s": [0.1] * 6}), layout)
    start = parse_run_start({"kind": "start", "position_rad": position, "velocity_rad_s": [0, 0, 0, 0, 0, 50.0]})
    with pytest.raises(TargetConfigError, match=r"velocity_rad_s\[5\]: 50 rad/s is beyond joint"):
        check_run_start(start, layout)


def test_the_server_layout_carries_the_urdf_limits() -> None:
    from sim_target.server import _urdf_limits

    config = load_target_config(DEPLOY / "target.virtual.yaml")
    layout = _layout()
    effort, velocity = _urdf_limits(config, layout.joint_names)
    assert effort == layout.effort_nm and velocity == layout.velocity_limit_rad_s
    assert effort is not None and all(0 < e < 1000 for e in effort)
