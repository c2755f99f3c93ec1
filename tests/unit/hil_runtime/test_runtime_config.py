"""The runtime config: one-line errors naming the file and the field (exit code 2); bundles that do
not match the drives refused before any I/O; ``hil run`` with bad input exits 2, drives never enabled."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from pydantic import ValidationError

from drivers.testing import FakeJointBus
from hil_runtime.bundle import BundleError
from hil_runtime.conditions import ConditionError
from hil_runtime.config import (
    RuntimeConfigError,
    load_runtime_config,
    parse_runtime_config,
)
from hil_runtime.runtime import Runtime
from sim_target.testing.ur5 import PD_BUNDLE
from tests.unit.hil_runtime.support import config_dict


def _write(tmp_path: Path, data: object, name: str = "runtime.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return path


def _refused(tmp_path: Path, data: object, *fragments: str) -> str:
    path = _write(tmp_path, data)
    with pytest.raises(RuntimeConfigError) as info:
        load_runtime_config(path)
    text = str(info.value)
    assert info.value.exit_code == 2
    assert "\n" not in text
    assert text.startswith(str(path)), text
    for fragment in fragments:
        assert fragment in text, text
    return text


def test_a_valid_config_loads_frozen_with_paths_relative_to_the_file(tmp_path: Path) -> None:
    data = config_dict(
        bundle={"path": "bundles/pd"},
        control_socket="run/rt.sock",
        reference={"kind": "condition", "condition": "C1", "conditions_file": "c.yaml"},
    )
    config = load_runtime_config(_write(tmp_path, data))
    assert config.bundle.path == tmp_path / "bundles" / "pd"
    assert config.control_socket == tmp_path / "run" / "rt.sock"
    assert config.reference.conditions_file == tmp_path / "c.yaml"
    assert config.period_s == 0.001 and len(config.joint_names) == 6
    with pytest.raises(ValidationError):
        config.robot = "other"  # type: ignore[misc]  # a frozen field assigned on purpose: refused


def test_telemetry_files_are_relative_to_the_config_not_to_the_working_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from hil_runtime.telemetry.auth import write_users_file

    folder = tmp_path / "etc"
    folder.mkdir()
    write_users_file(folder / "zenoh-users", {"operator": "s3cret"})
    (folder / "z.json5").write_text('{ listen: { endpoints: ["tcp/127.0.0.1:7447"] } }')
    telemetry = {"controls_enabled": True, "zenoh_config": "z.json5", "auth": {"users_file": "zenoh-users"}}
    path = _write(folder, config_dict(telemetry=telemetry))
    monkeypatch.chdir(tmp_path)  # the daemon started from elsewhere: the files are still the config's
    config = load_runtime_config(path)
    assert config.telemetry.zenoh_config == folder / "z.json5"
    assert config.telemetry.auth is not None and config.telemetry.auth.users_file == folder / "zenoh-users"


@pytest.mark.parametrize(
    ("change", "fragments"),
    [
        ({"bundle": {"path": "x", "mode": "mpc"}}, ["bundle.mode"]),
        ({"loop": {"pacing": "fast"}}, ["loop.pacing"]),
        ({"loop": {"fifo_priority": 120}}, ["loop.fifo_priority"]),
        ({"loop": {"period_s": 0.001}}, ["loop.period_s", "Extra inputs"]),
        ({"reference": {"kind": "condition"}}, ["reference", "condition: required"]),
        ({"reference": {"kind": "condition", "condition": "C1", "ramp_s": -1}}, ["reference.ramp_s"]),
        ({"safety": {"velocity_limit_rad_s": [1, 1, 1]}}, ["safety.velocity_limit_rad_s", "3 values for 6 joints"]),
        ({"safety": {"position_lower_rad": [0] * 6, "position_upper_rad": [0] * 6}}, ["position_lower_rad"]),
        ({"robot": None}, ["robot"]),
        ({"telemetry": {"enabled": "maybe"}}, ["telemetry.enabled"]),
    ],
)
def test_bad_fields_are_named(tmp_path: Path, change: dict, fragments: list[str]) -> None:
    data = config_dict()
    data.update(change)
    _refused(tmp_path, data, *fragments)


def test_bad_drive_bus_fields_are_named_with_their_path(tmp_path: Path) -> None:
    data = config_dict()
    data["bus"]["joints"][2]["node_id"] = 200
    _refused(tmp_path, data, "bus.joints.2.node_id")
    data = config_dict()
    del data["bus"]["period_s"]
    _refused(tmp_path, data, "bus.period_s")


def test_a_bus_over_its_load_budget_is_refused(tmp_path: Path) -> None:
    data = config_dict()
    data["bus"]["transport"] = {"interface": "virtual", "fd": False}  # six drives at 1 kHz, classical CAN
    _refused(tmp_path, data, "bus")


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(RuntimeConfigError, match="absent.yaml: file not found"):
        load_runtime_config(tmp_path / "absent.yaml")
    _refused(tmp_path, "robot: [unclosed\n", "not valid YAML")
    _refused(tmp_path, "- a list\n", "mapping")


@pytest.mark.parametrize(
    ("change", "error", "fragment"),
    [
        ({"robot": "ur10"}, RuntimeConfigError, "for 'ur5_paper'"),
        ({"bus_period": 0.002}, BundleError, "control period"),
        ({"drop_joint": True}, BundleError, "6 joints, the config has 5"),
        ({"swap_joints": True}, BundleError, "joint order"),
    ],
)
def test_a_bundle_that_does_not_match_the_drives_is_refused_before_any_io(
    tmp_path: Path, change: dict, error: type[RuntimeConfigError | BundleError], fragment: str
) -> None:
    data = config_dict()
    if "robot" in change:
        data["robot"] = change["robot"]
    if "bus_period" in change:
        data["bus"]["period_s"] = change["bus_period"]
    if change.get("drop_joint"):
        data["bus"]["joints"] = data["bus"]["joints"][:5]
    if change.get("swap_joints"):
        joints = data["bus"]["joints"]
        joints[0]["name"], joints[1]["name"] = joints[1]["name"], joints[0]["name"]
    config = parse_runtime_config(data, "rt.yaml")
    bus = FakeJointBus(len(data["bus"]["joints"]), period_s=config.period_s)
    with pytest.raises(error) as info:
        Runtime(config, bus)
    assert isinstance(info.value, (RuntimeConfigError, BundleError))  # pytest.raises types it as their base
    assert info.value.exit_code == 2 and fragment in str(info.value) and "\n" not in str(info.value)
    assert bus.events == []  # nothing was touched


def test_a_pinned_urdf_sha256_must_be_the_bundles(tmp_path: Path) -> None:
    bundle_sha = json.loads((PD_BUNDLE / "manifest.json").read_text())["robot"]["urdf_sha256"]
    same = parse_runtime_config(config_dict(bundle={"path": str(PD_BUNDLE), "urdf_sha256": bundle_sha}), "rt.yaml")
    Runtime(same, FakeJointBus(6))  # the arm's description is the bundle's: accepted
    other = parse_runtime_config(config_dict(bundle={"path": str(PD_BUNDLE), "urdf_sha256": "0" * 64}), "rt.yaml")
    bus = FakeJointBus(6)
    with pytest.raises(RuntimeConfigError) as info:
        Runtime(other, bus)
    text = str(info.value)
    assert text.startswith("rt.yaml: bundle.urdf_sha256: 000000000000") and bundle_sha[:12] in text, text
    assert info.value.exit_code == 2 and "\n" not in text and bus.events == []
    _refused(tmp_path, config_dict(bundle={"path": str(PD_BUNDLE), "urdf_sha256": "abc"}), "bundle.urdf_sha256")


def test_a_tampered_bundle_is_refused(tmp_path: Path) -> None:
    bundle = tmp_path / "pd"
    shutil.copytree(PD_BUNDLE, bundle)
    with open(bundle / "policy.onnx", "ab") as handle:
        handle.write(b"\0")
    config = parse_runtime_config(config_dict(bundle={"path": str(bundle)}))
    with pytest.raises(BundleError, match="sha256 mismatch"):
        Runtime(config, FakeJointBus(6))


def test_conditions_missing_file_unknown_name_and_out_of_limits(tmp_path: Path) -> None:
    missing = parse_runtime_config(
        config_dict(reference={"kind": "condition", "condition": "C1", "conditions_file": str(tmp_path / "none.yaml")})
    )
    with pytest.raises(ConditionError, match="file not found"):
        Runtime(missing, FakeJointBus(6))
    unknown = parse_runtime_config(config_dict(reference={"kind": "condition", "condition": "C9"}), "rt.yaml")
    with pytest.raises(RuntimeConfigError, match=r"reference.condition: no condition 'C9'.*known: C1, C2"):
        Runtime(unknown, FakeJointBus(6))
    tight = parse_runtime_config(
        config_dict(reference={"kind": "condition", "condition": "C4"}, safety={"velocity_limit_rad_s": [0.1] * 6})
    )
    with pytest.raises(ConditionError, match="velocity"):
        Runtime(tight, FakeJointBus(6))


def _hil(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "hil_runtime.cli", *args], capture_output=True, text=True, timeout=timeout, check=False
    )


def test_hil_run_refuses_bad_input_with_one_line_and_exit_2(tmp_path: Path) -> None:
    bad = config_dict()
    bad["bus"]["joints"][0]["max_torque_nm"] = -1
    result = _hil("run", "--config", str(_write(tmp_path, bad)))
    assert result.returncode == 2, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "bus.joints.0.max_torque_nm" in lines[0], result.stderr
    assert "Traceback" not in result.stderr


def test_hil_run_with_an_unreachable_bus_exits_2_without_enabling(tmp_path: Path) -> None:
    data = config_dict()
    data["bus"]["transport"] = {
        "interface": "remote",
        "bridge_host": "127.0.0.1",
        "bridge_port": 9,
        "fd": True,
        "data_bitrate": 5_000_000,
    }  # nothing listens on port 9
    result = _hil("run", "--config", str(_write(tmp_path, data)))
    assert result.returncode == 2, result.stderr
    assert "error:" in result.stderr and "bus:" in result.stderr and "Traceback" not in result.stderr
    assert "state ACTIVE" not in result.stderr


def test_hil_run_with_silent_drives_exits_2_without_enabling(tmp_path: Path) -> None:
    data = config_dict(control_socket=str(tmp_path / "rt.sock"))
    data["bus"]["state_change_timeout_s"] = 0.2  # nobody answers on this virtual channel
    result = _hil("run", "--config", str(_write(tmp_path, data)))
    assert result.returncode == 2, result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "no boot-up message" in errors[0], result.stderr
    assert "state ACTIVE" not in result.stderr
    assert not (tmp_path / "rt.sock").exists()


def test_hil_status_without_a_daemon(tmp_path: Path) -> None:
    result = _hil("status", "--socket", str(tmp_path / "none.sock"))
    assert result.returncode == 2 and "is hil run running" in result.stderr


@pytest.mark.parametrize("name", ["runtime.bridge.yaml", "runtime.ipc.yaml", "runtime.can0.yaml"])
def test_the_deployed_configs_are_valid(name: str) -> None:
    from tests.unit.hil_runtime.support import ROOT

    config = load_runtime_config(ROOT / "deploy" / name)
    assert config.robot == "ur5_paper" and config.period_s == 0.001
    if name != "runtime.can0.yaml":  # can0 names the installed bundle under /opt
        Runtime(config, FakeJointBus(6))  # bundle, joints, period and condition all agree


def test_hil_run_check_validates_without_touching_the_bus(tmp_path: Path) -> None:
    from tests.unit.hil_runtime.support import ROOT

    result = _hil("run", "--config", str(ROOT / "deploy" / "runtime.ipc.yaml"), "--check")
    assert result.returncode == 0, result.stderr
    assert "runtime.ipc.yaml: ok" in result.stdout and "reference C1" in result.stdout
    data = config_dict()
    data["bus"]["period_s"] = 0.002
    result = _hil("run", "--config", str(_write(tmp_path, data)), "--check")
    assert result.returncode == 2 and "control period" in result.stderr


def test_the_runtime_has_one_stale_feedback_budget(tmp_path: Path) -> None:
    """safety.max_stale_cycles is the one budget (FAULT stale_feedback): the runtime's drive bus
    counts none of its own, and a config that names bus.max_missed_cycles too must agree."""
    from hil_runtime.factory import runtime_drive_bus

    def with_budgets(missed: int | None, stale: int) -> dict:
        data = config_dict(safety={"max_stale_cycles": stale})
        if missed is not None:
            data["bus"]["max_missed_cycles"] = missed
        return data

    for missed, stale in ((None, 3), (3, 3), (1, 1)):  # the old deploy configs named both, equal
        config = parse_runtime_config(with_budgets(missed, stale), "r.yaml")
        assert config.safety.max_stale_cycles == stale
        assert runtime_drive_bus(config).max_missed_cycles is None
    with pytest.raises(
        RuntimeConfigError, match=r"^r\.yaml: .*bus\.max_missed_cycles 25 differs from safety\.max_stale_cycles 1"
    ):
        parse_runtime_config(with_budgets(25, 1), "r.yaml")


def test_the_hybrid_wait_spins_by_default_only_on_a_cpu_of_its_own(tmp_path: Path) -> None:
    def spin_of(**loop: object) -> float:
        data = config_dict()
        data["loop"] = {**data["loop"], "pacing": "clock", **loop}
        config = parse_runtime_config(data, "r.yaml")
        runtime = Runtime(config, FakeJointBus(6), bundle=None)
        assert runtime.pacer.spin_s == config.loop_spin_s
        return config.loop_spin_s

    assert spin_of() == 0.0  # a shared CPU: spinning would take it from the others
    assert spin_of(cpu_affinity=[0]) == pytest.approx(100e-6)
    assert spin_of(cpu_affinity=[0], pacing="bus") == 0.0  # nothing to wait for
    assert spin_of(cpu_affinity=[0], spin_s=0.0) == 0.0
    assert spin_of(spin_s=50e-6) == pytest.approx(50e-6)
    _refused(tmp_path, config_dict(loop={"spin_s": 0.0005}), "loop.spin_s", "half the period")


def test_an_lmpc_bundle_that_would_chatter_on_the_stated_sensing_is_refused_before_any_io(tmp_path: Path) -> None:
    # The shipped ur5_paper PD bundle turns the noise target (3e-4 rad, 0.2 rad/s) into ~8 N m steps
    # on the shoulder, above the 1.17 N m per period the rate bound allows; the default sensing (1e-5 rad,
    # differenced) into ~0.5 N m: accepted. The law alone (mode fb) is not gated.
    Runtime(parse_runtime_config(config_dict(), "rt.yaml"), FakeJointBus(6))
    noisy = {"path": str(PD_BUNDLE), "encoder_noise_rad": 3e-4, "velocity_noise_rad_s": 0.2}
    bus = FakeJointBus(6)
    with pytest.raises(RuntimeConfigError) as info:
        Runtime(parse_runtime_config(config_dict(bundle=noisy), "rt.yaml"), bus)
    text = str(info.value)
    assert text.startswith("rt.yaml: bundle.encoder_noise_rad: bundle "), text
    assert "on joint 2" in text and "1.17 N m" in text and "tolerates about" in text, text
    assert info.value.exit_code == 2 and "\n" not in text and bus.events == []
    Runtime(parse_runtime_config(config_dict(bundle={**noisy, "mode": "fb"}), "rt.yaml"), FakeJointBus(6))
    negative = config_dict(bundle={"path": str(PD_BUNDLE), "encoder_noise_rad": -1e-5})
    _refused(tmp_path, negative, "bundle.encoder_noise_rad")
