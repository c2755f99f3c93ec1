"""JointState CDR and the RIHS01 hash against libraries this project did not write (rosbags,
mcap-ros2-support)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from hil_runtime.formats.ros2 import (
    JOINT_STATE,
    JOINT_STATE_DEFINITION,
    JointStateEncoder,
    decode_joint_state,
    rihs01,
)

rosbags_typesys = pytest.importorskip("rosbags.typesys")
mcap_ros2_dynamic = pytest.importorskip("mcap_ros2._dynamic")

UR5 = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")


def _typestore() -> Any:
    return rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)


def test_rihs01_of_joint_state_is_what_rosbags_computes() -> None:
    expected = _typestore().hash_rihs01(JOINT_STATE)
    assert rihs01(JOINT_STATE) == expected
    assert expected.startswith("RIHS01_") and len(expected) == 7 + 64


@pytest.mark.parametrize(
    ("names", "frame_id"),
    [(UR5, ""), (("a", "bb", "ccc"), "base_link"), ((), ""), (("j1",), "x" * 7)],
)
def test_cdr_is_byte_identical_to_rosbags_and_decodes_in_both_libraries(names: tuple[str, ...], frame_id: str) -> None:
    n = len(names)
    rng = np.random.default_rng(n)
    q, qd, tau = rng.normal(size=(3, n))
    stamp_ns = 1_764_000_000_987_654_321
    data = JointStateEncoder(names, frame_id).encode(stamp_ns, q, qd, tau)

    store = _typestore()
    msg = store.deserialize_cdr(data, JOINT_STATE)
    assert list(msg.name) == list(names) and msg.header.frame_id == frame_id
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == divmod(stamp_ns, 1_000_000_000)
    np.testing.assert_array_equal(msg.position, q)
    np.testing.assert_array_equal(msg.velocity, qd)
    np.testing.assert_array_equal(msg.effort, tau)
    assert bytes(store.serialize_cdr(msg, JOINT_STATE)) == data  # the same bytes, padding included

    decoders = mcap_ros2_dynamic.generate_dynamic(JOINT_STATE, JOINT_STATE_DEFINITION)
    decoded = decoders[JOINT_STATE](data)
    assert list(decoded.name) == list(names)
    np.testing.assert_array_equal(decoded.effort, tau)

    ours = decode_joint_state(data)
    assert ours["stamp_ns"] == stamp_ns and ours["name"] == list(names)
    np.testing.assert_array_equal(ours["velocity"], qd)


def test_our_decoder_refuses_truncated_or_foreign_bytes() -> None:
    data = JointStateEncoder(UR5).encode(0, np.zeros(6), np.zeros(6), np.zeros(6))
    for bad in (data[:-9], data[:20], b"\x00\x00\x00\x00" + data[4:]):
        with pytest.raises(ValueError):
            decode_joint_state(bad)
