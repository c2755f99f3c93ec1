"""TelemetryConfig: defaults, loopback-only endpoints, one-line errors; make_sink's choices."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil_runtime.telemetry import (
    NullTelemetry,
    TelemetryConfig,
    TelemetryConfigError,
    make_sink,
    parse_telemetry_config,
)
from hil_runtime.telemetry.auth import TelemetryAuth
from hil_runtime.telemetry.config import publisher_zenoh_config, zenoh_config
from hil_runtime.telemetry.publisher import ZenohTelemetry


def test_defaults_are_off_and_loopback() -> None:
    config = TelemetryConfig()
    assert not config.enabled and config.mode == "peer"
    assert config.listen == ("tcp/127.0.0.1:7447",) and config.connect == ()
    assert not config.controls_enabled and config.state_decimation == 1
    assert config.key_prefix("ur5_paper") == "hil/ur5_paper"
    assert TelemetryConfig(robot="left_arm").key_prefix("ur5_paper") == "hil/left_arm"


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"listen": ["tcp/192.0.2.3:7447"]}, "endpoint 'tcp/192.0.2.3:7447' is not loopback"),
        ({"connect": ["tcp/example.org:7447"]}, "is not loopback"),
        ({"listen": ["tcp/198.51.100.7:7447"]}, "is not loopback"),
        ({"listen": ["tcp/[::]:7447"]}, "is not loopback"),
        ({"listen": ["127.0.0.1:7447"]}, "is not 'proto/host:port'"),
        ({"listen": ["tcp/127.0.0.1"]}, "missing or bad port"),
        ({"listen": ["carrier-pigeon/127.0.0.1:1"]}, "unknown protocol 'carrier-pigeon'"),
        ({"robot": "arm/1"}, "cannot be a Zenoh key chunk"),
        ({"robot": "*"}, "cannot be a Zenoh key chunk"),
        ({"state_decimation": 0}, "state_decimation"),
        ({"queue_size": 1}, "queue_size"),
        ({"mode": "router"}, "mode"),
        ({"mode": "client"}, "client mode needs connect endpoints"),
        ({"listen": [], "connect": []}, "peer mode needs a listen or connect endpoint"),
        ({"zenoh_config": "/nonexistent/zenoh.json5"}, "is not a file"),
        ({"controls": True}, "controls: Extra inputs are not permitted"),
    ],
)
def test_bad_sections_fail_in_one_line(data: dict, message: str) -> None:
    with pytest.raises(TelemetryConfigError) as info:
        parse_telemetry_config(data, "runtime.yaml")
    text = str(info.value)
    assert text.startswith("runtime.yaml: ") and message in text and "\n" not in text
    assert info.value.exit_code == 2


def test_remote_endpoints_need_allow_remote() -> None:
    config = parse_telemetry_config({"listen": ["tcp/192.0.2.9:7447"], "allow_remote": True})
    assert config.listen == ("tcp/192.0.2.9:7447",)
    assert parse_telemetry_config({"listen": ["tcp/[::1]:7447", "tcp/localhost:7448"]}).listen[0] == "tcp/[::1]:7447"
    assert parse_telemetry_config(None) == TelemetryConfig()


def test_zenoh_config_never_scouts() -> None:
    conf = zenoh_config("peer", ["tcp/127.0.0.1:7447"], [])
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(conf.get_json("mode")) == "peer"


def test_publisher_session_drops_at_once_and_declares_a_short_lease() -> None:
    conf = publisher_zenoh_config(TelemetryConfig(enabled=True, lease_s=0.8))
    assert json.loads(conf.get_json("transport/link/tx/lease")) == 800
    assert json.loads(conf.get_json("transport/link/tx/queue/congestion_control/drop/wait_before_drop")) == 50
    assert json.loads(conf.get_json("transport/link/tx/queue/size/data_high")) == 16


def test_json5_file_keeps_its_endpoints_unless_set(tmp_path: Path) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text(
        '{ // a comment: json5\n listen: { endpoints: ["tcp/127.0.0.1:17000"] },'
        " scouting: { multicast: { enabled: true } } }"
    )
    from_file = publisher_zenoh_config(TelemetryConfig(enabled=True, zenoh_config=path))
    assert json.loads(from_file.get_json("listen/endpoints")) == ["tcp/127.0.0.1:17000"]
    assert json.loads(from_file.get_json("scouting/multicast/enabled")) is False  # forced off whatever the file says
    explicit = publisher_zenoh_config(TelemetryConfig(enabled=True, zenoh_config=path, listen=("tcp/127.0.0.1:17001",)))
    assert json.loads(explicit.get_json("listen/endpoints")) == ["tcp/127.0.0.1:17001"]
    bad = tmp_path / "bad.json5"
    bad.write_text("{ listen: ")
    with pytest.raises(TelemetryConfigError, match="bad.json5: not a valid Zenoh json5 config"):
        parse_telemetry_config({"enabled": True, "zenoh_config": str(bad)})


class _Controls:
    def request_stop(self) -> None: ...

    def request_reset(self, activate: bool | None = None) -> None: ...


def test_make_sink_choices(tmp_path: Path) -> None:
    info = {"joints": ["a", "b"]}
    users = tmp_path / "users"
    users.write_text("operator:secret\n")
    users.chmod(0o600)
    controlled = TelemetryConfig(enabled=True, controls_enabled=True, auth=TelemetryAuth(users_file=users))
    assert isinstance(make_sink(TelemetryConfig(), "arm", info), NullTelemetry)
    sink = make_sink(TelemetryConfig(enabled=True), "arm", info, controls=_Controls())
    assert isinstance(sink, ZenohTelemetry) and sink._controls is None  # controls not enabled: not wired
    sink = make_sink(controlled, "arm", info, controls=_Controls())
    assert isinstance(sink, ZenohTelemetry) and sink._controls is not None
    with pytest.raises(TelemetryConfigError, match="controls_enabled: the runtime passed no controls"):
        make_sink(controlled, "arm", info, controls=None)
    with pytest.raises(TelemetryConfigError, match=r"info\['joints'\] must list the joint names"):
        make_sink(TelemetryConfig(enabled=True), "arm", {})
    with pytest.raises(TelemetryConfigError, match="telemetry: robot .* cannot be a Zenoh key chunk"):
        make_sink(TelemetryConfig(enabled=True), "my arm/2", info)
