"""The target's loopback bridge: a python-can-remote client in another process shares the target's
in-process virtual bus, both ways."""

from __future__ import annotations

import subprocess
import sys
import uuid

import can

from drivers.transport import start_bridge_server

CLIENT = r"""
import sys, can
bus = can.Bus(interface="remote", channel=sys.argv[1])
bus.send(can.Message(arbitration_id=0x201, data=b"\x0f\x00\x10\x00", is_extended_id=False))
reply = bus.recv(timeout=10)
print(hex(reply.arbitration_id), reply.data.hex())
bus.shutdown()
"""


def test_a_remote_process_shares_the_virtual_bus() -> None:
    channel = f"bridge-{uuid.uuid4().hex[:8]}"
    bridge = start_bridge_server("127.0.0.1", 0, channel)  # port 0: any free loopback port
    local = can.Bus(interface="virtual", channel=channel)
    try:
        client = subprocess.Popen(
            [sys.executable, "-c", CLIENT, bridge.url],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        request = local.recv(timeout=20)
        assert client.stderr is not None  # stderr=PIPE
        assert request is not None, client.stderr.read() if client.poll() is not None else "no frame"
        assert request.arbitration_id == 0x201 and bytes(request.data) == b"\x0f\x00\x10\x00"
        local.send(can.Message(arbitration_id=0x181, data=bytes(range(8)), is_extended_id=False))
        out, err = client.communicate(timeout=20)
        assert client.returncode == 0, err
        assert out.split() == ["0x181", "0001020304050607"]
    finally:
        local.shutdown()
        bridge.close()
