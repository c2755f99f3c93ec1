"""The ``telemetry.ros2`` section: off by default, ROS names checked in one line."""

from __future__ import annotations

import pytest

from hil_runtime.formats.rmw_zenoh import data_key, mangle
from hil_runtime.telemetry.config import TelemetryConfigError, parse_telemetry_config


def test_off_by_default() -> None:
    assert parse_telemetry_config({"enabled": True}).ros2.enabled is False


@pytest.mark.parametrize(
    ("section", "field"),
    [
        ({"node": "hil-runtime"}, "ros2.node"),
        ({"topic": "joint_states"}, "ros2.topic"),
        ({"namespace": "/arm 1"}, "ros2.namespace"),
        ({"domain_id": 300}, "ros2.domain_id"),
        ({"decimation": 0}, "ros2.decimation"),
        ({"qos": "x"}, "ros2.qos"),
    ],
)
def test_bad_ros2_sections_are_one_line(section: dict[str, object], field: str) -> None:
    with pytest.raises(TelemetryConfigError, match=field.replace(".", r"\.")) as info:
        parse_telemetry_config({"enabled": True, "ros2": {"enabled": True, **section}}, "rt.yaml: telemetry")
    assert "\n" not in str(info.value) and "rt.yaml" in str(info.value)


def test_names_as_key_chunks() -> None:
    assert mangle("/") == "%" and mangle("/arm1/joint_states") == "%arm1%joint_states"
    assert data_key(3, "/arm1", "/joint_states", "RIHS01_x").startswith("3/arm1/joint_states/")
    assert (
        data_key(0, "/", "/joint_states", "RIHS01_x") == "0/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_x"
    )
