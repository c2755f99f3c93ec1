"""Config validation: frozen, one-line errors naming file and field, loopback-only bridge."""

from pathlib import Path

import pydantic
import pytest

from drivers.cia402.od import EDS_PATH, EdsError, load_object_dictionary, lookup_variable
from drivers.config import load_drive_bus_config, parse_drive_bus_config
from drivers.errors import BusLoadError, DriveConfigError


def _joints(n: int) -> list[dict]:
    return [{"name": f"j{i}", "node_id": i + 1, "max_torque_nm": 150.0} for i in range(n)]


def test_valid_fd_config_is_frozen() -> None:
    config = parse_drive_bus_config(
        {"transport": {"fd": True, "data_bitrate": 5_000_000}, "period_s": 0.001, "joints": _joints(6)}
    )
    assert config.joints[0].effective_rated_torque_mnm == 5000
    with pytest.raises(pydantic.ValidationError):
        config.period_s = 0.01  # type: ignore[misc]  # a frozen field assigned on purpose: the refusal under test


def test_yaml_error_names_file_and_field(tmp_path: Path) -> None:
    path = tmp_path / "arm.yaml"
    path.write_text("period_s: 0.01\njoints:\n  - {name: a, node_id: 300, max_torque_nm: 1}\n")
    with pytest.raises(DriveConfigError, match=r"arm.yaml: joints\.0\.node_id: ") as info:
        load_drive_bus_config(path)
    assert "\n" not in str(info.value)


def test_bus_load_refused_at_load(tmp_path: Path) -> None:
    path = tmp_path / "fast.yaml"
    path.write_text(
        "period_s: 0.001\njoints:\n"
        + "".join(f"  - {{name: j{i}, node_id: {i + 1}, max_torque_nm: 10}}\n" for i in range(6))
    )
    with pytest.raises(BusLoadError, match="fast.yaml: 6 drives"):
        load_drive_bus_config(path)


@pytest.mark.parametrize("host", ["192.0.2.10", "example.com"])
def test_remote_bridge_must_be_loopback(host: str) -> None:
    with pytest.raises(DriveConfigError, match="not loopback"):
        parse_drive_bus_config(
            {"transport": {"interface": "remote", "bridge_host": host}, "period_s": 0.01, "joints": _joints(1)}
        )


def test_ipv6_loopback_bridge_url() -> None:
    config = parse_drive_bus_config(
        {
            "transport": {"interface": "remote", "bridge_host": "::1", "bridge_port": 5000},
            "period_s": 0.01,
            "joints": _joints(1),
        }
    )
    assert config.transport.remote_url == "ws://[::1]:5000/"


def test_torque_out_of_int16_range_refused() -> None:
    with pytest.raises(DriveConfigError, match="joints.0: .*at least 4578 mN·m"):
        parse_drive_bus_config(
            {"period_s": 0.01, "joints": [{"name": "a", "node_id": 1, "max_torque_nm": 150, "rated_torque_mnm": 1000}]}
        )


def test_eds_shipped_is_valid() -> None:
    variable = lookup_variable(load_object_dictionary(3), 0x1800, 1)
    assert variable is not None and variable.default == 0x183


def test_bad_eds_names_file_and_object(tmp_path: Path) -> None:
    broken = tmp_path / "broken.eds"
    broken.write_text(
        EDS_PATH.read_text().replace(
            "[6077]\nParameterName=Torque actual value\nObjectType=0x7\nDataType=0x0003",
            "[6077]\nParameterName=Torque actual value\nObjectType=0x7\nDataType=0x0007",
        )
    )
    with pytest.raises(EdsError, match=r"broken.eds: \[6077\] sub 0: DataType 0x0007"):
        load_object_dictionary(1, broken)
    missing = tmp_path / "missing.eds"
    with pytest.raises(EdsError, match="missing.eds: EDS file not found"):
        load_object_dictionary(1, missing)
