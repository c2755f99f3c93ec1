"""The ``ipc`` interface across real processes (tests/integration/test_ipc_bus.py has the buses in
one process): frames both ways in order, a killed peer dropped and its stale socket removed."""

from __future__ import annotations

import signal
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from drivers.ipc import IpcBus
from tests.integration.test_ipc_bus import _msg, _recv, _sockets

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the ipc bus is Linux only")


@pytest.fixture
def bus_dir(tmp_path: Path) -> Path:
    return tmp_path / "bus"


ECHO = r"""
import sys, can
bus = can.Bus(interface="ipc", channel=sys.argv[1], fd=True)
print("ready", flush=True)
while True:
    msg = bus.recv(10.0)
    if msg is None or msg.arbitration_id == 0x7FF:
        break
    bus.send(can.Message(arbitration_id=msg.arbitration_id + 1, data=msg.data, is_fd=msg.is_fd,
                         is_extended_id=False, bitrate_switch=msg.bitrate_switch))
bus.shutdown()
"""

SLEEPER = r"""
import sys, time, can
bus = can.Bus(interface="ipc", channel=sys.argv[1])
print("ready", flush=True)
time.sleep(60)
"""


def _start(script: str, bus_dir: Path) -> subprocess.Popen[str]:
    process = subprocess.Popen(
        [sys.executable, "-c", script, str(bus_dir)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    assert process.stdout is not None
    line = process.stdout.readline()
    if line.strip() != "ready":
        process.kill()
        raise AssertionError(f"peer did not start: {line} {process.stderr.read() if process.stderr else ''}")
    return process


def test_frames_cross_two_real_processes_both_ways_in_order(bus_dir: Path) -> None:
    bus_dir.mkdir()
    echo = _start(ECHO, bus_dir)
    bus = IpcBus(bus_dir, fd=True)
    try:
        for i in range(500):
            fd = i % 2 == 0
            bus.send(_msg(0x100, i.to_bytes(2, "little") + bytes(10 if fd else 0), is_fd=fd, bitrate_switch=fd))
            reply = bus.recv(5.0)
            assert reply is not None and reply.arbitration_id == 0x101 and reply.is_fd == fd
            assert int.from_bytes(reply.data[:2], "little") == i
        bus.send(_msg(0x7FF))
        assert echo.wait(10) == 0, echo.stderr.read() if echo.stderr else ""
        assert bus.recv(0.5) is None  # the echo peer left: EOF handled, nothing raised
        assert bus.peer_count == 0 and bus.stats.peers_left == 1
    finally:
        if echo.poll() is None:
            echo.kill()
        bus.shutdown()


def test_a_killed_peer_is_dropped_and_its_stale_socket_removed_by_the_next_joiner(bus_dir: Path) -> None:
    bus_dir.mkdir()
    victim = _start(SLEEPER, bus_dir)
    a = IpcBus(bus_dir)
    b = IpcBus(bus_dir)
    try:
        assert len(_sockets(bus_dir)) == 3
        victim.send_signal(signal.SIGKILL)
        victim.wait(10)
        for i in range(3):  # sending to a dead peer neither raises nor blocks
            a.send(_msg(0x10 + i))
        assert [_recv(b, 2.0).arbitration_id for _ in range(3)] == [0x10, 0x11, 0x12]
        assert a.peer_count == 1 and a.stats.peers_left == 1
        assert len(_sockets(bus_dir)) == 3  # a SIGKILLed process cannot remove its socket file...
        c = IpcBus(bus_dir)  # ...the next joiner finds it refused and removes it
        try:
            assert c.stats.stale_sockets_removed == 1 and c.peer_count == 2
            assert len(_sockets(bus_dir)) == 3
            assert all(stat.S_ISSOCK((bus_dir / s).lstat().st_mode) for s in _sockets(bus_dir))
        finally:
            c.shutdown()
    finally:
        if victim.poll() is None:
            victim.kill()
        a.shutdown()
        b.shutdown()
