"""``hil telemetry foxglove``: the Zenoh telemetry republished live to Foxglove (docs/formats.md).

A Foxglove WebSocket server (the ``foxglove-sdk`` package; 127.0.0.1:8765 by default) with:

| topic | schema | what |
|---|---|---|
| ``/joint_states`` | ``sensor_msgs/msg/JointState`` (JSON) | measured q [rad], q̇ [rad/s], applied τ [N·m] |
| ``/joint_reference`` | ``sensor_msgs/msg/JointState`` (JSON) | q_ref, q̇_ref, the law's τ_fb |
| ``/tf`` | ``foxglove.FrameTransforms`` | each URDF joint at the measured q; under ``reference/`` at q_ref |
| ``/robot_description`` | ``std_msgs/msg/String`` (JSON) | the arm's URDF (republished every second) |
| ``/hil/cycle`` ``/hil/stats`` ``/hil/status`` ``/hil/events`` | JSON schemas of the MCAP record | |

States are republished at ``rate_hz`` at most (the telemetry runs at the loop's rate; a browser
does not need 1 kHz); stats, status and events as they come. Log times are the runtime's clock.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hil_runtime.formats.mcap_record import JSON_SCHEMAS
from hil_runtime.formats.urdf import JointFrame, joint_frames

_ARRAY = {"type": "array", "items": {"type": "number"}}
JOINT_STATE_JSON_SCHEMA = {
    "type": "object",
    "properties": {
        "header": {
            "type": "object",
            "properties": {
                "stamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
                "frame_id": {"type": "string"},
            },
        },
        "name": {"type": "array", "items": {"type": "string"}},
        "position": _ARRAY,
        "velocity": _ARRAY,
        "effort": _ARRAY,
    },
}
STRING_JSON_SCHEMA = {"type": "object", "properties": {"data": {"type": "string"}}}
REFERENCE_PREFIX = "reference/"  # /tf frames of the reference arm (q_ref)


class FoxgloveError(ValueError):
    """The server cannot start (port in use, a non-loopback host, foxglove-sdk missing); exit 2."""

    exit_code = 2


def _json_channel(foxglove: Any, topic: str, name: str, schema: dict[str, Any]) -> Any:
    return foxglove.Channel(
        topic,
        message_encoding="json",
        schema=foxglove.Schema(name=name, encoding="jsonschema", data=json.dumps(schema).encode()),
    )


class FoxgloveBridge:
    """Channels on a running Foxglove server, fed from telemetry callbacks (any thread)."""

    def __init__(
        self,
        joints: Sequence[str],
        urdf_text: str | None,
        host: str = "127.0.0.1",
        port: int = 8765,
        rate_hz: float = 50.0,
        name: str = "hil-runtime",
    ) -> None:
        try:
            import foxglove
            from foxglove.channels import FrameTransformsChannel
        except ImportError:
            raise FoxgloveError(
                "hil telemetry foxglove needs foxglove-sdk: pip install 'hil-runtime[formats]'"
            ) from None
        self._messages = __import__("foxglove.messages", fromlist=["FrameTransforms"])
        self.joints = list(joints)
        self.urdf_text = urdf_text
        self.frames: list[JointFrame] = joint_frames(urdf_text) if urdf_text else []
        self._index = {name: i for i, name in enumerate(self.joints)}
        self._min_interval_ns = int(1e9 / rate_hz)
        self._last_state_ns = 0
        self.states_in = 0
        self.states_out = 0
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port)
        except Exception as exc:  # noqa: BLE001 - the SDK's errors are untyped (a bind failure is the usual one)
            raise FoxgloveError(f"--port {port}: cannot start the Foxglove server on {host} ({exc})") from None
        self.port = int(self.server.port)
        self.host = host
        self._channels = {
            "/joint_states": _json_channel(
                foxglove, "/joint_states", "sensor_msgs/msg/JointState", JOINT_STATE_JSON_SCHEMA
            ),
            "/joint_reference": _json_channel(
                foxglove, "/joint_reference", "sensor_msgs/msg/JointState", JOINT_STATE_JSON_SCHEMA
            ),
            "/robot_description": _json_channel(
                foxglove, "/robot_description", "std_msgs/msg/String", STRING_JSON_SCHEMA
            ),
            **{
                topic: _json_channel(foxglove, topic, name, JSON_SCHEMAS[name])
                for topic, name in (
                    ("/hil/cycle", "hil/Cycle"),
                    ("/hil/stats", "hil/Stats"),
                    ("/hil/status", "hil/Status"),
                    ("/hil/events", "hil/Event"),
                )
            },
        }
        self._tf = FrameTransformsChannel("/tf")
        self._stop = threading.Event()
        self._describer = threading.Thread(target=self._describe_every_second, name="foxglove-urdf", daemon=True)
        self._describer.start()

    def _describe_every_second(self) -> None:
        # Foxglove has no latched topics: a panel opened later gets the URDF within a second.
        while not self._stop.is_set():
            if self.urdf_text:
                self._channels["/robot_description"].log({"data": self.urdf_text}, log_time=time.time_ns())
            self._stop.wait(1.0)

    def _joint_state(self, t_ns: int, position: np.ndarray, velocity: np.ndarray, effort: np.ndarray) -> dict[str, Any]:
        sec, nsec = divmod(t_ns, 1_000_000_000)
        return {
            "header": {"stamp": {"sec": sec, "nsec": nsec}, "frame_id": ""},
            "name": self.joints,
            "position": position.tolist(),
            "velocity": velocity.tolist(),
            "effort": effort.tolist(),
        }

    def on_state(self, sample: Any, t_ns: int, seq: int) -> None:
        """A decoded telemetry state (``StateSample``: q, qd, q_ref, qd_ref, tau, tau_fb, fallback, compute_s)."""
        self.states_in += 1
        if t_ns - self._last_state_ns < self._min_interval_ns:
            return
        self._last_state_ns = t_ns
        q = np.asarray(sample["q"])
        self._channels["/joint_states"].log(self._joint_state(t_ns, q, sample["qd"], sample["tau"]), log_time=t_ns)
        self._channels["/joint_reference"].log(
            self._joint_state(t_ns, np.asarray(sample["q_ref"]), sample["qd_ref"], sample["tau_fb"]), log_time=t_ns
        )
        self._channels["/hil/cycle"].log(
            {"seq": seq, "fallback": float(sample["fallback"]), "compute_s": float(sample["compute_s"])}, log_time=t_ns
        )
        if self.frames:
            self._tf.log(self._transforms(q, np.asarray(sample["q_ref"]), t_ns), log_time=t_ns)
        self.states_out += 1

    def _transforms(self, q: np.ndarray, q_ref: np.ndarray, t_ns: int) -> Any:
        """The measured arm's link frames, and the reference arm's under ``reference/`` (a second
        URDF layer with that frame prefix draws it beside the measured one)."""
        m = self._messages
        stamp = m.Timestamp(sec=t_ns // 1_000_000_000, nsec=t_ns % 1_000_000_000)

        def transform(parent: str, child: str, translation: Any, rotation: Any) -> Any:
            return m.FrameTransform(
                timestamp=stamp,
                parent_frame_id=parent,
                child_frame_id=child,
                translation=m.Vector3(x=translation[0], y=translation[1], z=translation[2]),
                rotation=m.Quaternion(x=rotation[0], y=rotation[1], z=rotation[2], w=rotation[3]),
            )

        transforms = []
        for prefix, positions in (("", q), (REFERENCE_PREFIX, q_ref)):
            for frame in self.frames:
                i = self._index.get(frame.name)
                translation, rotation = frame.transform(float(positions[i]) if i is not None else 0.0)
                transforms.append(transform(prefix + frame.parent, prefix + frame.child, translation, rotation))
        root = self.frames[0].parent  # the reference arm stands where the measured one does
        transforms.append(transform(root, REFERENCE_PREFIX + root, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
        return m.FrameTransforms(transforms=transforms)

    def on_json(self, topic: str, body: dict[str, Any], t_ns: int) -> None:
        self._channels[topic].log(body, log_time=t_ns)

    def close(self) -> None:
        self._stop.set()
        self._describer.join(2.0)
        self.server.stop()


def run_bridge(client: Any, bridge: FoxgloveBridge, seconds: float | None, stop: threading.Event | None = None) -> None:
    """Subscribe the bridge to a :class:`~hil_runtime.telemetry.subscriber.TelemetryClient` and
    serve until ``seconds`` pass (None: until ``stop`` is set or Ctrl-C)."""
    from hil_runtime.telemetry.codec import TelemetryDecodeError, decode_header

    schema = client.schema()

    def on_state(payload: bytes) -> None:
        try:
            header = decode_header(payload)
            if header.warmup:
                return
            bridge.on_state(schema.decode_state(payload), header.t_ns, header.seq)
        except TelemetryDecodeError:
            return  # counted by nobody: a live view skips what it cannot read

    def json_forwarder(topic: str, decode: Any) -> Any:
        def forward(payload: bytes) -> None:
            try:
                header, body = decode(payload)
            except TelemetryDecodeError:
                return
            if not header.warmup:
                bridge.on_json(topic, body, header.t_ns)

        return forward

    client.subscribe("state", on_state)
    client.subscribe("stats", json_forwarder("/hil/stats", schema.decode_stats))
    client.subscribe("status", json_forwarder("/hil/status", schema.decode_status))
    client.subscribe("events", json_forwarder("/hil/events", schema.decode_event))
    (stop or threading.Event()).wait(seconds)


def urdf_text_for(client: Any, robot: str, explicit: Path | None) -> str | None:
    """The arm's URDF for the 3D panel (see :func:`hil_runtime.formats.mcap_record.urdf_of_bundle_document`)."""
    from hil_runtime.formats.mcap_record import urdf_of_bundle_document
    from hil_runtime.telemetry.subscriber import TelemetryUnavailable

    try:
        bundle = client.query_json("bundle")
    except TelemetryUnavailable:
        bundle = None
    path = urdf_of_bundle_document(bundle, robot, explicit)
    return path.read_text() if path is not None else None
