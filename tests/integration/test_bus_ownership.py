"""The ipc bus and the control sockets belong to their user (issue 20, docs/security.md): a bus
directory made by another user is refused, not joined; the bus's files are private; a peer of
another uid is refused; each frame carries its sender; a control socket another user put at the
configured path is refused by the clients. The hostile side runs as a second, unprivileged user."""

from __future__ import annotations

import json
import os
import socket
import stat
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from drivers.config import TransportConfig
from drivers.errors import DriveConfigError
from drivers.ipc import IpcBus, IpcMessage, bus_directory
from drivers.ipc.bus import open_bus as open_ipc_bus
from drivers.json_socket import JsonLineServer, OwnershipError, request_json_line
from hil_runtime.control import ControlError, send_command
from tests.other_user import OtherUser, other_user, run_as, shared_dir

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Unix sockets, SO_PEERCRED")
__all__ = ["other_user", "shared_dir"]  # fixtures used by name below

SQUAT_DIRECTORY = "import os, sys; os.mkdir(sys.argv[1], 0o755); print('made', flush=True)"

# Listens at argv[1] as the squatter and answers every line with {"ok": true}: a fake runtime.
FAKE_SERVER = """
import os, socket, sys
s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
s.bind(sys.argv[1]); os.chmod(sys.argv[1], 0o777); s.listen(8)
print("listening", flush=True)
while True:
    c, _ = s.accept()
    c.recv(4096)
    c.sendall(b'{"ok": true, "state": "ACTIVE"}\\n')
    c.close()
"""


def _wait_line(proc: subprocess.Popen[str], expected: str) -> None:
    assert proc.stdout is not None and proc.stderr is not None  # piped, text
    line = proc.stdout.readline()
    assert line.strip() == expected, proc.stderr.read()


@pytest.fixture
def fake_server(other_user: OtherUser, shared_dir: Path) -> Iterator[Path]:
    path = shared_dir / "hil-runtime.sock"
    proc = run_as(other_user, FAKE_SERVER, str(path))
    try:
        _wait_line(proc, "listening")
        yield path
    finally:
        proc.kill()
        proc.wait()


def test_the_bus_directory_is_private_and_its_sockets_are_not_0755(tmp_path: Path) -> None:
    bus_dir = tmp_path / "a" / "bus"
    bus = IpcBus(bus_dir)
    try:
        assert stat.S_IMODE(os.stat(bus_dir).st_mode) == 0o700
        assert stat.S_IMODE(os.stat(bus_dir.parent).st_mode) == 0o700
        (sock,) = bus_dir.glob("*.sock")
        assert stat.S_IMODE(os.stat(sock).st_mode) == 0o600
    finally:
        bus.shutdown()


def test_with_a_group_the_directory_is_0770_and_the_sockets_0660(tmp_path: Path, other_user: OtherUser) -> None:
    bus = IpcBus(tmp_path / "bus", group=str(other_user.gid))
    try:
        st = os.stat(tmp_path / "bus")
        assert (stat.S_IMODE(st.st_mode), st.st_gid) == (0o770, other_user.gid)
        (sock,) = (tmp_path / "bus").glob("*.sock")
        assert stat.S_IMODE(os.stat(sock).st_mode) == 0o660
    finally:
        bus.shutdown()


def test_a_bus_directory_made_first_by_another_user_is_refused(other_user: OtherUser, shared_dir: Path) -> None:
    squatted = shared_dir / "hil-can"
    proc = run_as(other_user, SQUAT_DIRECTORY, str(squatted))
    _wait_line(proc, "made")
    proc.wait()
    assert os.stat(squatted).st_uid == other_user.uid
    with pytest.raises(can.CanInitializationError, match=f"belongs to {other_user.name}"):
        IpcBus(squatted)
    assert list(squatted.iterdir()) == []  # nothing of ours went in
    config = TransportConfig(interface="ipc", channel=str(squatted))
    with pytest.raises(DriveConfigError, match="not joined") as refused:
        open_ipc_bus(config)
    assert refused.value.exit_code == 2


@pytest.mark.parametrize("mode", [0o777, 0o1777, 0o770])
def test_a_directory_writable_by_others_is_refused(tmp_path: Path, mode: int) -> None:
    bus_dir = tmp_path / "bus"
    bus_dir.mkdir()
    os.chmod(bus_dir, mode)
    with pytest.raises(can.CanInitializationError, match="writable by"):
        IpcBus(bus_dir)


def test_a_directory_under_another_users_directory_is_refused(other_user: OtherUser, tmp_path: Path) -> None:
    parent = tmp_path / "theirs"
    parent.mkdir(mode=0o755)
    os.chown(parent, other_user.uid, other_user.gid)  # she could rename our bus away and put hers
    with pytest.raises(can.CanInitializationError, match=f"belongs to {other_user.name}"):
        IpcBus(parent / "bus")


def test_a_peer_of_another_uid_is_refused(other_user: OtherUser, shared_dir: Path, tmp_path: Path) -> None:
    """Her listening socket inside our bus directory (as a group-shared bus would let her): not joined."""
    theirs = shared_dir / "x.sock"
    code = (
        "import socket, sys, time; s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET); "
        "s.bind(sys.argv[1]); s.listen(8); print('listening', flush=True); time.sleep(30)"
    )
    proc = run_as(other_user, code, str(theirs))
    try:
        _wait_line(proc, "listening")
        bus_dir = tmp_path / "bus"
        bus_dir.mkdir(mode=0o700)
        os.link(theirs, bus_dir / "999-squat.sock")  # the same socket, now in our directory
        bus = IpcBus(bus_dir)
        try:
            assert bus.peer_count == 0
            assert bus.stats.peers_refused == 1
        finally:
            bus.shutdown()
    finally:
        proc.kill()
        proc.wait()


def test_each_frame_carries_its_sender(tmp_path: Path) -> None:
    rx, a, b = IpcBus(tmp_path / "bus"), IpcBus(tmp_path / "bus"), IpcBus(tmp_path / "bus")
    try:
        a.send(can.Message(arbitration_id=0x183, data=b"\x01", is_extended_id=False))
        b.send(can.Message(arbitration_id=0x183, data=b"\x02", is_extended_id=False))
        got = [rx.recv(1.0) for _ in range(2)]
        assert all(isinstance(msg, IpcMessage) and msg.sender is not None for msg in got)
        senders = {bytes(m.data): m.sender for m in got if isinstance(m, IpcMessage)}
        assert senders[b"\x01"] != senders[b"\x02"]
        assert {s.pid for s in senders.values() if s is not None} == {os.getpid()}
    finally:
        for bus in (rx, a, b):
            bus.shutdown()


def test_a_bare_name_lives_in_the_users_runtime_directory(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_RUNTIME_DIR", "/run/user/1000")
    assert bus_directory("hil") == Path("/run/user/1000/hil-can/hil")
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    assert bus_directory("hil") == Path("/run/hil/can/hil")
    assert bus_directory("/srv/can") == Path("/srv/can")


def test_a_control_socket_owned_by_another_user_is_refused(fake_server: Path, other_user: OtherUser) -> None:
    with pytest.raises(OwnershipError, match=f"belongs to {other_user.name}"):
        request_json_line(fake_server, {"command": "stop"}, 2.0)
    with pytest.raises(ControlError, match=f"control socket {fake_server}: .*belongs to {other_user.name}"):
        send_command(fake_server, "stop")


def test_hil_stop_refuses_a_squatted_socket_exit_2(fake_server: Path, hil_command: list[str]) -> None:
    import subprocess

    done = subprocess.run(
        [*hil_command, "stop", "--socket", str(fake_server)], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2, done.stdout + done.stderr
    assert "stop requested" not in done.stdout
    assert "belongs to" in done.stderr and "Traceback" not in done.stderr


def test_a_socket_served_by_another_uid_is_refused_even_in_our_directory(
    other_user: OtherUser, shared_dir: Path, tmp_path: Path
) -> None:
    """SO_PEERCRED: our own file name, her process behind it (a hard link to her socket)."""
    theirs = shared_dir / "s.sock"
    proc = run_as(other_user, FAKE_SERVER, str(theirs))
    try:
        _wait_line(proc, "listening")
        ours = tmp_path / "runtime.sock"
        os.link(theirs, ours)
        os.chown(ours, 0, 0, follow_symlinks=False)  # the file now says root...
        with pytest.raises(OwnershipError, match="served by"):  # ...the kernel says who listens
            request_json_line(ours, {"command": "status"}, 2.0)
    finally:
        proc.kill()
        proc.wait()


def test_our_own_socket_still_answers(tmp_path: Path) -> None:
    server = JsonLineServer(
        tmp_path / "c.sock", lambda line: {"ok": True, "echo": json.loads(line)}, in_use_by="x", thread_name="t"
    )
    try:
        assert request_json_line(tmp_path / "c.sock", {"a": 1}, 2.0) == {"ok": True, "echo": {"a": 1}}
    finally:
        server.close()


def test_a_client_of_a_service_runtime_directory_accepts_the_service_user(
    other_user: OtherUser, tmp_path: Path
) -> None:
    """/run/hil (User=hil, RuntimeDirectory=hil): her socket in her own directory under root's, fine."""
    service_dir = tmp_path / "run-hil"
    service_dir.mkdir(mode=0o750)
    os.chown(service_dir, other_user.uid, other_user.gid)
    path = service_dir / "runtime.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.bind(str(path))
    os.chown(path, other_user.uid, other_user.gid)
    from drivers.ownership import check_socket_owner

    try:
        check_socket_owner(path)  # no error: only she (or root) could have put it there
        os.chmod(service_dir, 0o770)  # her group may write there too: no longer hers alone
        with pytest.raises(OwnershipError):
            check_socket_owner(path)
    finally:
        sock.close()
