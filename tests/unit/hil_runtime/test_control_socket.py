"""The daemon's control socket: status / reset / activate / stop set requests; bad lines answered
with an error; a stale socket file is replaced, a live one refused; the file is group-only."""

from __future__ import annotations

import json
import socket
import stat
import threading
from pathlib import Path
from typing import Any

import pytest

from hil_runtime.control import (
    ControlError,
    ControlServer,
    handle_command,
    send_command,
)


class Target:
    def __init__(self) -> None:
        self.requests: list[str] = []

    def status(self) -> dict[str, Any]:
        return {"state": "FAULT", "fault": "heartbeat_lost: drive 5"}

    def request_stop(self) -> None:
        self.requests.append("stop")

    def request_reset(self) -> None:
        self.requests.append("reset")

    def request_activate(self) -> None:
        self.requests.append("activate")


@pytest.mark.parametrize("command", ["status", "reset", "activate", "stop"])
def test_commands(command: str) -> None:
    target = Target()
    reply = handle_command(target, json.dumps({"command": command}))
    assert reply["ok"] and reply["state"] == "FAULT"
    assert target.requests == ([] if command == "status" else [command])


@pytest.mark.parametrize(
    ("line", "error"), [("{", "not JSON"), ('{"command": "fly"}', "unknown command"), ("[1]", "unknown command")]
)
def test_bad_requests_are_answered_not_raised(line: str, error: str) -> None:
    reply = handle_command(Target(), line)
    assert reply["ok"] is False and error in reply["error"]


def test_over_the_socket(tmp_path: Path) -> None:
    path = tmp_path / "run" / "rt.sock"
    target = Target()
    server = ControlServer(path, target)
    try:
        assert stat.S_IMODE(path.stat().st_mode) & 0o007 == 0  # no access for others
        assert send_command(path, "status")["fault"] == "heartbeat_lost: drive 5"
        assert send_command(path, "reset")["ok"]
        assert target.requests == ["reset"]
        with pytest.raises(ControlError, match="another runtime"):
            ControlServer(path, Target())
    finally:
        server.close()
    assert not path.exists()
    with pytest.raises(ControlError, match="is hil run running"):
        send_command(path, "status")


def test_a_stale_socket_file_is_replaced(tmp_path: Path) -> None:
    path = tmp_path / "rt.sock"
    dead = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    dead.bind(str(path))
    dead.close()  # the file stays, nobody listens: a runtime that died
    server = ControlServer(path, Target())
    try:
        assert send_command(path, "status")["ok"]
    finally:
        server.close()


def test_a_regular_file_at_the_socket_path_is_refused_and_kept(tmp_path: Path) -> None:
    path = tmp_path / "rt.sock"
    path.write_text("not a socket")
    with pytest.raises(ControlError, match=r"rt.sock: exists and is not a socket; not removed"):
        ControlServer(path, Target())
    assert path.read_text() == "not a socket"


def test_a_server_that_closes_without_answering_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "mute.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as mute:
        mute.bind(str(path))
        mute.listen(1)

        def hang_up() -> None:
            connection, _ = mute.accept()
            connection.recv(1024)  # the request arrives; the server hangs up without a reply
            connection.close()

        thread = threading.Thread(target=hang_up)
        thread.start()
        with pytest.raises(ControlError, match=r"mute.sock: the server closed the connection without answering"):
            send_command(path, "status", timeout_s=5.0)
        thread.join(5.0)


def test_hil_activate_asks_the_daemon_to_activate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The local way back to ACTIVE after a Zenoh reset (which stops at INACTIVE, docs/security.md)."""
    from hil_runtime.cli import main

    path = tmp_path / "rt.sock"
    target = Target()
    server = ControlServer(path, target)
    try:
        assert main(["activate", "--socket", str(path)]) == 0
    finally:
        server.close()
    assert target.requests == ["activate"]
    assert "activation requested (state was FAULT)" in capsys.readouterr().out
