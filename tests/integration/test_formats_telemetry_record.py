"""``hil telemetry record --out x.mcap`` from a live (fake) 1 kHz loop over Zenoh, read back with
mcap's reader and mcap-ros2-support's decoder: the values offered, in order, nearly none lost;
then ``hil telemetry plot x.mcap``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from models.lab.ports import free_loopback_port

pytest.importorskip("zenoh")
mcap_reader = pytest.importorskip("mcap.reader")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")

from tests.integration.telemetry_fake_loop import JOINTS, FakeLoop, expected_state  # noqa: E402
from tests.integration.test_telemetry_zenoh import _hil  # noqa: E402


def test_telemetry_record_writes_an_mcap_that_standard_readers_open(tmp_path: Path) -> None:
    loop = FakeLoop(free_loopback_port(), seconds=40.0)
    out = tmp_path / "live.mcap"
    try:
        result = _hil("telemetry", "record", "--connect", loop.endpoint, "--seconds", "2", "--out", str(out))
        assert result.returncode == 0, result.stderr
    finally:
        loop.kill()
    with out.open("rb") as stream:
        reader = mcap_reader.make_reader(stream)
        seqs = [json.loads(m.data)["seq"] for _, _, m in reader.iter_messages(topics=["/hil/cycle"])]
        raw = {topic: list(reader.iter_messages(topics=[topic])) for topic in ("/joint_states", "/joint_reference")}
        attachments = {a.name for a in reader.iter_attachments()}
        stats = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=["/hil/stats"])]
    schema = raw["/joint_states"][0][0]
    assert schema is not None and schema.name == "sensor_msgs/msg/JointState" and schema.encoding == "ros2msg"
    decode = mcap_ros2_decoder.DecoderFactory().decoder_for("cdr", schema)
    assert decode is not None
    rows = (0, len(seqs) // 2, len(seqs) - 1)
    states = {row: decode(raw["/joint_states"][row][2].data) for row in rows}
    references = {row: decode(raw["/joint_reference"][row][2].data) for row in rows}
    assert (
        len(seqs) == len(raw["/joint_states"]) == len(raw["/joint_reference"]) >= 1000
    )  # 2 s at 1 kHz, a loaded machine may lag
    assert np.all(np.diff(seqs) > 0)
    lost = seqs[-1] - seqs[0] + 1 - len(seqs)
    assert lost <= 0.001 * len(seqs), f"{lost} lost"
    for row in rows:
        expected = expected_state(seqs[row])
        assert list(states[row].name) == list(JOINTS)
        np.testing.assert_array_equal(states[row].position, expected["q"])
        np.testing.assert_array_equal(states[row].effort, expected["tau"])
        np.testing.assert_array_equal(references[row].position, expected["q_ref"])
        np.testing.assert_array_equal(references[row].effort, expected["tau_fb"])
    assert {"config.json", "bundle.json"} <= attachments
    assert stats and all("rate_hz" in item and "telemetry_sent" in item for item in stats)

    pytest.importorskip("matplotlib")
    plotted = _hil("telemetry", "plot", str(out))
    assert plotted.returncode == 0, plotted.stderr
    assert (tmp_path / "live_torque.png").read_bytes()[:4] == b"\x89PNG"
