"""issue 20: the runtime's Zenoh session as it will really be (file and fields merged): loopback
endpoints only, controls only with authenticated peers, a users file only its owner reads."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil_runtime.telemetry import TelemetryConfigError, parse_telemetry_config
from hil_runtime.telemetry.auth import write_users_file
from hil_runtime.telemetry.config import publisher_zenoh_config

pytest.importorskip("zenoh")


@pytest.mark.parametrize(
    ("json5", "message"),
    [
        ('{ listen: { endpoints: ["tcp/0.0.0.0:7447"] } }', "listen/endpoints 'tcp/0.0.0.0:7447' is not loopback"),
        ('{ listen: { endpoints: ["tcp/192.0.2.4:7447"] } }', "listen/endpoints 'tcp/192.0.2.4:7447' is not loopback"),
        (
            '{ listen: { endpoints: ["tcp/127.0.0.1:7447"] }, connect: { endpoints: ["tcp/198.51.100.2:7447"] } }',
            "connect/endpoints 'tcp/198.51.100.2:7447' is not loopback",
        ),
        ('{ listen: { endpoints: { peer: ["udp/[::]:7447"] } } }', "listen/endpoints 'udp/[::]:7447' is not loopback"),
        ("{ mode: 'peer' }", "listen/endpoints 'tcp/[::]:0' (Zenoh's default: the file sets none) is not loopback"),
    ],
)
def test_a_zenoh_config_file_with_remote_endpoints_is_refused(tmp_path: Path, json5: str, message: str) -> None:
    path = tmp_path / "z.json5"
    path.write_text(json5)
    with pytest.raises(TelemetryConfigError) as info:
        parse_telemetry_config({"enabled": True, "zenoh_config": str(path)}, "rt.yaml")
    text = str(info.value)
    assert text.startswith("rt.yaml: ") and f"zenoh_config '{path}'" in text and message in text, text
    assert "\n" not in text and info.value.exit_code == 2
    # allow_remote is the decision that lets them through
    assert parse_telemetry_config({"enabled": True, "zenoh_config": str(path), "allow_remote": True}).allow_remote


def test_explicit_loopback_endpoints_win_over_the_file(tmp_path: Path) -> None:
    path = tmp_path / "z.json5"
    path.write_text('{ listen: { endpoints: ["tcp/0.0.0.0:7447"] } }')
    config = parse_telemetry_config({"zenoh_config": str(path), "listen": ["tcp/127.0.0.1:7447"]})
    assert json.loads(publisher_zenoh_config(config).get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]


def _users(tmp_path: Path) -> Path:
    return write_users_file(tmp_path / "users", {"operator": "s3cret", "viewer": "v1ew"})


def test_controls_need_authenticated_peers(tmp_path: Path) -> None:
    with pytest.raises(TelemetryConfigError, match="controls_enabled: the stop/reset queryables need authenticated"):
        parse_telemetry_config({"controls_enabled": True}, "rt.yaml")
    users = _users(tmp_path)
    config = parse_telemetry_config({"controls_enabled": True, "auth": {"users_file": str(users)}})
    conf = publisher_zenoh_config(config)
    assert json.loads(conf.get_json("transport/auth/usrpwd/dictionary_file")) == str(users)
    assert json.loads(conf.get_json("access_control/enabled")) is False  # everyone in the file may control
    # or the dictionary in the json5 file
    path = tmp_path / "z.json5"
    path.write_text(
        json.dumps(
            {
                "listen": {"endpoints": ["tcp/127.0.0.1:7447"]},
                "transport": {"auth": {"usrpwd": {"dictionary_file": str(users)}}},
            }
        )
    )
    assert parse_telemetry_config({"controls_enabled": True, "zenoh_config": str(path)}).controls_enabled


def test_control_users_become_an_access_control_rule(tmp_path: Path) -> None:
    users = _users(tmp_path)
    config = parse_telemetry_config(
        {"controls_enabled": True, "auth": {"users_file": str(users), "control_users": ["operator"]}}
    )
    acl = json.loads(publisher_zenoh_config(config).get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "allow"
    assert acl["subjects"][0]["usernames"] == ["viewer"]
    assert acl["rules"][0]["permission"] == "deny" and acl["rules"][0]["messages"] == ["query"]
    assert acl["rules"][0]["key_exprs"] == ["hil/*/stop", "hil/*/reset"]


@pytest.mark.parametrize(
    ("content", "mode", "auth", "message"),
    [
        ("operator:s3cret\n", 0o644, {}, "is readable or writable by others (mode 0644); chmod 600 it"),
        ("operator:s3cret\n", 0o620, {}, "readable or writable by others"),
        ("operator\n", 0o600, {}, "line 1: not 'user:password'"),
        ("", 0o600, {}, "no 'user:password' line"),
        ("operator:s3cret\n", 0o600, {"control_users": ["root"]}, "control_users: 'root' not in users_file"),
        (None, 0o600, {}, "does not exist"),
    ],
)
def test_bad_users_files_are_one_line(tmp_path: Path, content: str | None, mode: int, auth: dict, message: str) -> None:
    path = tmp_path / "users"
    if content is not None:
        path.write_text(content)
        path.chmod(mode)
    with pytest.raises(TelemetryConfigError) as info:
        parse_telemetry_config({"controls_enabled": True, "auth": {"users_file": str(path), **auth}}, "rt.yaml")
    text = str(info.value)
    assert text.startswith("rt.yaml: auth") and message in text and "\n" not in text, text


def test_control_users_and_a_file_with_its_own_access_control_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "z.json5"
    path.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:7447"] }, access_control: { enabled: true } }')
    data = {
        "zenoh_config": str(path),
        "controls_enabled": True,
        "auth": {"users_file": str(_users(tmp_path)), "control_users": ["operator"]},
    }
    with pytest.raises(TelemetryConfigError, match="access_control is set and so is auth.control_users"):
        parse_telemetry_config(data, "rt.yaml")


def test_a_dictionary_named_by_the_zenoh_config_file_is_held_to_the_same_rules(tmp_path: Path) -> None:
    users = tmp_path / "users"
    users.write_text("operator:s3cret\n")
    users.chmod(0o644)
    path = tmp_path / "z.json5"
    document = {
        "listen": {"endpoints": ["tcp/127.0.0.1:7447"]},
        "transport": {"auth": {"usrpwd": {"dictionary_file": str(users)}}},
    }
    path.write_text(json.dumps(document))
    with pytest.raises(TelemetryConfigError, match="is readable or writable by others"):
        parse_telemetry_config({"controls_enabled": True, "zenoh_config": str(path)}, "rt.yaml")
