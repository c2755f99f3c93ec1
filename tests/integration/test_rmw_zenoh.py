"""``telemetry.ros2``: /joint_states as rmw_zenoh publishes it, checked against rmw_zenoh's
docs/design.md (key expression, attachment, liveliness tokens) and decoded by rosbags, a CDR
library this project did not write; the type hash is the one rosbags computes."""

from __future__ import annotations

import re
import threading
import time
from typing import Any

import numpy as np
import pytest

from models.lab.ports import free_loopback_port

zenoh = pytest.importorskip("zenoh")
rosbags_typesys = pytest.importorskip("rosbags.typesys")

from zenoh.ext import Int64, z_deserialize  # noqa: E402 - after the importorskip

from hil_runtime.telemetry import CycleState, TelemetryConfig, make_sink  # noqa: E402
from hil_runtime.telemetry.config import zenoh_config  # noqa: E402

JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
DDS_TYPE = "sensor_msgs::msg::dds_::JointState_"
# From design.md: @ros2_lv/<domain>/<zid>/<nid>/<id>/<entity>/<enclave>/<namespace>/<node>[/<topic>/<type>/<hash>/<qos>]
NODE_TOKEN = re.compile(r"^@ros2_lv/(\d+)/([0-9a-f]+)/(\d+)/(\d+)/NN/%/([^/]+)/([^/]+)$")
PUBLISHER_TOKEN = re.compile(
    r"^@ros2_lv/(\d+)/([0-9a-f]+)/(\d+)/(\d+)/MP/%/([^/]+)/([^/]+)/([^/]+)/([^/]+)/([^/]+)/([^/]+)$"
)


def _state(k: int) -> CycleState:
    base = np.linspace(-1.0, 1.0, 6) + 1e-3 * k
    return CycleState(k, time.monotonic_ns(), base, base * 2, base, base, base * 3, base, 0.0, 1e-5)


@pytest.mark.parametrize(("namespace", "domain_id"), [("/", 0), ("/arm1", 7)])
def test_joint_states_follow_rmw_zenoh_s_design(namespace: str, domain_id: int) -> None:
    port = free_loopback_port()
    config = TelemetryConfig.model_validate(
        {
            "enabled": True,
            "listen": [f"tcp/127.0.0.1:{port}"],
            "ros2": {"enabled": True, "domain_id": domain_id, "namespace": namespace, "decimation": 2},
        }
    )
    sink = make_sink(config, "ur5", {"joints": JOINTS})
    received: list[tuple[str, bytes, bytes]] = []
    lock = threading.Lock()

    def on_sample(sample: Any) -> None:
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else b""
        with lock:
            received.append((str(sample.key_expr), sample.payload.to_bytes(), attachment))

    sink.start()
    session = zenoh.open(zenoh_config("peer", [], [f"tcp/127.0.0.1:{port}"]))
    try:
        session.declare_subscriber(f"{domain_id}/**", on_sample)
        deadline = time.monotonic() + 10
        tokens: list[str] = []
        while time.monotonic() < deadline and len(tokens) < 2:
            tokens = [
                str(reply.ok.key_expr) for reply in session.liveliness().get(f"@ros2_lv/{domain_id}/**") if reply.ok
            ]
            time.sleep(0.05)
        time.sleep(0.3)  # the subscription reaches the publisher
        sent = [_state(k) for k in range(1, 41)]
        for state in sent:
            sink.offer_state(state)
            time.sleep(0.002)
        time.sleep(0.5)
    finally:
        sink.close()
        session.close()

    store = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)
    type_hash = store.hash_rihs01("sensor_msgs/msg/JointState")
    topic = "arm1/joint_states" if namespace == "/arm1" else "joint_states"
    with lock:
        samples = list(received)
    assert len(samples) == 20  # every 2nd of 40
    gids = set()
    for i, (key, payload, attachment) in enumerate(samples):
        assert key == f"{domain_id}/{topic}/{DDS_TYPE}/{type_hash}"
        msg = store.deserialize_cdr(payload, "sensor_msgs/msg/JointState")
        state = sent[2 * i]
        assert list(msg.name) == JOINTS
        np.testing.assert_array_equal(msg.position, state.q)
        np.testing.assert_array_equal(msg.velocity, state.qd)
        np.testing.assert_array_equal(msg.effort, state.tau)
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        assert abs(stamp_ns - time.time_ns()) < 60e9  # wall time, not the monotonic clock
        names_and_values = z_deserialize(tuple[str, Int64, str, Int64, str, bytes], zenoh.ZBytes(attachment))
        assert names_and_values[0::2] == ("sequence_number", "source_timestamp", "source_gid")
        sequence_number, source_timestamp, gid = names_and_values[1::2]
        assert sequence_number == i + 1 and len(gid) == 16
        gids.add(gid)
        assert abs(source_timestamp - time.time_ns()) < 60e9
        assert len(attachment) == 77  # the Jazzy layout's size with a 16-byte gid

    node = [m for t in tokens if (m := NODE_TOKEN.match(t))]
    publisher = [m for t in tokens if (m := PUBLISHER_TOKEN.match(t))]
    assert len(node) == 1 and len(publisher) == 1, tokens
    n, p = node[0].groups(), publisher[0].groups()
    ns_chunk = "%arm1" if namespace == "/arm1" else "%"
    assert n[0] == p[0] == str(domain_id) and n[1] == p[1]  # same domain, same session id
    assert n[2] == n[3] == p[2] and p[3] != n[3]  # the node's id twice; the publisher its own id
    assert n[4:] == (ns_chunk, "hil_runtime")
    assert p[4:] == (ns_chunk, "hil_runtime", "%" + topic.replace("/", "%"), DDS_TYPE, type_hash, "::,10:,:,:,,")
    assert len(gids) == 1  # one publisher, one gid
