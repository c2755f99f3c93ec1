"""``hil telemetry foxglove``: a WebSocket client speaking foxglove.websocket.v1 (the websockets
package, not the SDK that serves) connects, gets the channel adverts, subscribes and receives the
arm's joint states, its transforms and its URDF, republished from live Zenoh telemetry."""

from __future__ import annotations

import json
import re
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from models.lab.ports import free_loopback_port

pytest.importorskip("zenoh")
pytest.importorskip("foxglove")
ws_client = pytest.importorskip("websockets.sync.client")

from hil_runtime.telemetry import CycleState, TelemetryConfig, make_sink  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
PD_BUNDLE = REPO / "models" / "bundles" / "ur5_paper" / "pd"
JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]


def test_a_foxglove_client_connects_sees_the_channels_and_receives_the_arm() -> None:
    zenoh_port = free_loopback_port()
    config = TelemetryConfig.model_validate({"enabled": True, "listen": [f"tcp/127.0.0.1:{zenoh_port}"]})
    sink = make_sink(config, "ur5_paper", {"joints": JOINTS, "bundle": {"path": str(PD_BUNDLE), "bundle_id": "pd:x"}})
    sink.start()
    stop = threading.Event()

    def loop() -> None:  # a fake 500 Hz loop
        k = 0
        while not stop.is_set():
            k += 1
            q = np.full(6, 0.001 * k)
            sink.offer_state(CycleState(k, time.monotonic_ns(), q, q, q, q, q * 10, q, 0.0, 1e-5))
            time.sleep(0.002)

    feeder = threading.Thread(target=loop, daemon=True)
    feeder.start()
    command = [sys.executable, "-m", "hil_runtime.cli", "telemetry", "foxglove", "--port", "0", "--seconds", "60"]
    command += ["--connect", f"tcp/127.0.0.1:{zenoh_port}", "--rate-hz", "100"]
    server = subprocess.Popen(command, stderr=subprocess.PIPE, text=True, cwd=REPO)
    try:
        assert server.stderr is not None
        line = server.stderr.readline()
        match = re.search(r"ws://127\.0\.0\.1:(\d+)", line)
        assert match and "URDF attached" in line, line
        # foxglove-sdk 0.30 names the protocol foxglove.sdk.v1 (the foxglove.websocket.v1 messages
        # under a new name); a client offers both, as Foxglove's app does.
        url = f"ws://127.0.0.1:{match.group(1)}"
        with ws_client.connect(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"]) as ws:
            assert ws.subprotocol in ("foxglove.sdk.v1", "foxglove.websocket.v1")
            channels: dict[str, dict[str, Any]] = {}
            deadline = time.monotonic() + 20
            while len(channels) < 8 and time.monotonic() < deadline:
                message = json.loads(ws.recv(timeout=10))
                if message["op"] == "advertise":
                    channels.update({c["topic"]: c for c in message["channels"]})
            assert {"/joint_states", "/joint_reference", "/tf", "/robot_description", "/hil/cycle"} <= set(channels)
            assert channels["/joint_states"]["schemaName"] == "sensor_msgs/msg/JointState"
            assert channels["/tf"]["schemaName"] == "foxglove.FrameTransforms"
            topics = ["/joint_states", "/tf", "/robot_description"]
            subscriptions = [{"id": i, "channelId": channels[t]["id"]} for i, t in enumerate(topics)]
            ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
            got: dict[str, bytes] = {}
            while len(got) < 3 and time.monotonic() < deadline + 10:
                frame = ws.recv(timeout=10)
                if isinstance(frame, bytes) and frame[0] == 0x01:  # message data
                    (subscription,) = struct.unpack_from("<I", frame, 1)
                    got.setdefault(topics[subscription], frame[1 + 4 + 8 :])
    finally:
        stop.set()
        server.terminate()
        server.wait(30)
        sink.close()
    state = json.loads(got["/joint_states"])
    assert state["name"] == JOINTS and len(state["position"]) == 6
    assert state["effort"] == pytest.approx([10 * p for p in state["position"]])
    assert "<robot" in json.loads(got["/robot_description"])["data"]
    assert b"shoulder_link" in got["/tf"] and b"flange" in got["/tf"]  # every link's frame
    assert b"reference/flange" in got["/tf"] and b"reference/base_link" in got["/tf"]  # the reference arm
