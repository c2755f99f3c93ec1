"""``/joint_states`` for ROS 2 over Zenoh, without ROS 2: rmw_zenoh's conventions (docs/formats.md).

With ``telemetry.ros2.enabled`` the telemetry publisher thread also publishes each state sample
(every ``ros2.decimation``-th) as a ``sensor_msgs/msg/JointState`` the way rmw_zenoh_cpp (ROS 2
Jazzy) does, so ``ros2 topic echo /joint_states`` on a host running rmw_zenoh and connected to the
same Zenoh router sees the arm. From rmw_zenoh's docs/design.md:

- data key expression ``<domain_id>/<topic without its leading '/'>/<DDS type name>/<type hash>``,
  e.g. ``0/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_a13e…``;
- payload: the message in CDR (little-endian, :mod:`hil_runtime.formats.ros2`);
- a per-sample attachment, serialised with zenoh-ext (``zenoh.ext.z_serialize``) as rmw_zenoh
  Jazzy writes it: ``"sequence_number"`` int64, ``"source_timestamp"`` int64 (wall clock ns at
  publication), ``"source_gid"`` 16 bytes;
- liveliness tokens for the graph: the node
  ``@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>`` and the publisher
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>``,
  '/' in names written '%', an empty enclave or the root namespace as '%'.

header.stamp is the sample's time on the wall clock (the runtime's monotonic time plus the
offset measured at start): ROS tools expect wall time.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from hil_runtime.formats.ros2 import JOINT_STATE, JOINT_STATE_DDS, JointStateEncoder, rihs01

NODE_ID = 0  # rmw_zenoh numbers a context's entities from 0: the node first, then its publisher
PUBLISHER_ID = 1
# QoS chunk of the publisher's token: reliable, volatile, keep last 10 (defaults left empty):
# <reliability>:<durability>:<history>,<depth>:<deadline>:<lifespan>:<liveliness>,<lease>
QOS_KEEP_LAST_10 = "::,10:,:,:,,"


def mangle(name: str) -> str:
    """A ROS name as one key chunk: '/' written '%'; the root or an empty name is '%'."""
    return name.replace("/", "%") if name not in ("", "/") else "%"


def data_key(domain_id: int, namespace: str, topic: str, type_hash: str) -> str:
    fully_qualified = (namespace.rstrip("/") + "/" + topic.lstrip("/")).lstrip("/")
    return f"{domain_id}/{fully_qualified}/{JOINT_STATE_DDS}/{type_hash}"


def liveliness_tokens(
    domain_id: int, zid: str, namespace: str, node: str, topic: str, type_hash: str
) -> tuple[str, str]:
    """(node token, publisher token) for one node with one publisher."""
    base = f"@ros2_lv/{domain_id}/{zid}/{NODE_ID}"
    ns = mangle(namespace)
    fully_qualified = namespace.rstrip("/") + "/" + topic.lstrip("/")
    node_token = f"{base}/{NODE_ID}/NN/%/{ns}/{node}"
    publisher_token = (
        f"{base}/{PUBLISHER_ID}/MP/%/{ns}/{node}/{mangle(fully_qualified)}/{JOINT_STATE_DDS}/{type_hash}/"
        f"{QOS_KEEP_LAST_10}"
    )
    return node_token, publisher_token


def attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's per-sample attachment (Jazzy layout: each field after its name), by zenoh-ext."""
    from zenoh.ext import Int64, z_serialize

    return bytes(
        z_serialize(
            (
                "sequence_number",
                Int64(sequence_number),
                "source_timestamp",
                Int64(source_timestamp_ns),
                "source_gid",
                gid,
            )
        ).to_bytes()
    )


class JointStatePublisher:
    """One ROS 2 node with one ``sensor_msgs/msg/JointState`` publisher on a Zenoh session.

    Called from the telemetry publisher thread only (never from the loop)."""

    def __init__(
        self,
        session: Any,
        joints: Sequence[str],
        domain_id: int = 0,
        namespace: str = "/",
        node: str = "hil_runtime",
        topic: str = "/joint_states",
        frame_id: str = "",
        decimation: int = 1,
    ) -> None:
        import zenoh

        self.type_hash = rihs01(JOINT_STATE)
        self.key = data_key(domain_id, namespace, topic, self.type_hash)
        zid = str(session.info.zid())
        self.tokens = liveliness_tokens(domain_id, zid, namespace, node, topic, self.type_hash)
        self.gid = hashlib.sha256(self.tokens[1].encode()).digest()[:16]  # unique per publisher, as rmw's
        self.encoder = JointStateEncoder(tuple(joints), frame_id)
        self.decimation = decimation
        self.sequence_number = 0
        self.published = 0
        self._offered = 0
        self._n = len(joints)
        self._wall_minus_monotonic_ns = time.clock_gettime_ns(time.CLOCK_REALTIME) - time.monotonic_ns()
        self._publisher = session.declare_publisher(
            self.key, congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.DATA
        )
        liveliness = session.liveliness()
        self._declared = [liveliness.declare_token(token) for token in self.tokens]

    def publish(self, t_ns: int, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> None:
        """One sample (the runtime's monotonic ``t_ns``); every ``decimation``-th is sent."""
        self._offered += 1
        if (self._offered - 1) % self.decimation:
            return
        self.sequence_number += 1
        payload = self.encoder.encode(t_ns + self._wall_minus_monotonic_ns, q, qd, tau)
        self._publisher.put(payload, attachment=attachment(self.sequence_number, time.time_ns(), self.gid))
        self.published += 1

    def publish_state_payload(self, payload: bytes | bytearray) -> None:
        """From a telemetry ``state`` payload (docs/telemetry.md): q, q̇ and the applied τ."""
        n = self._n
        t_ns = int.from_bytes(payload[16:24], "little", signed=True)
        body = np.frombuffer(payload, dtype="<f8", offset=40, count=6 * n)
        self.publish(t_ns, body[0:n], body[n : 2 * n], body[4 * n : 5 * n])

    def close(self) -> None:
        for entity in (*self._declared, self._publisher):
            try:
                entity.undeclare()
            except Exception:  # noqa: BLE001, S110 - closing: the session goes next and drops them anyway
                pass
        self._declared = []
