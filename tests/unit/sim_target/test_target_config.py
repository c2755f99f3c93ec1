"""Target config: YAML and TOML, frozen, one-line errors naming file and field, exit code 2."""

from __future__ import annotations

from pathlib import Path

import pydantic
import pytest

from hil_runtime.cli import main as hil_main
from sim_target.config import (
    DriveFault,
    ImpulseFault,
    PayloadFault,
    TargetConfigError,
    load_target_config,
    parse_fault,
)

DEPLOY = Path(__file__).resolve().parents[3] / "deploy"


@pytest.mark.parametrize("name", ["target.virtual.yaml", "target.bridge.yaml"])
def test_shipped_configs_load(name: str) -> None:
    config = load_target_config(DEPLOY / name)
    assert config.bus.interface == "virtual"
    assert config.drives.node_ids == (1, 2, 3, 4, 5, 6)


def test_toml_and_yaml_give_the_same_config(tmp_path: Path) -> None:
    (tmp_path / "t.toml").write_text(
        'period_s = 0.004\nclock = "realtime"\n[bus]\nchannel = "x"\n'
        '[[faults]]\nkind = "payload"\nat_s = 1.0\nmass_kg = 2.0\n'
    )
    (tmp_path / "t.yaml").write_text(
        "period_s: 0.004\nclock: realtime\nbus: {channel: x}\nfaults: [{kind: payload, at_s: 1.0, mass_kg: 2.0}]\n"
    )
    assert load_target_config(tmp_path / "t.toml") == load_target_config(tmp_path / "t.yaml")
    assert load_target_config(tmp_path / "t.toml").faults == (PayloadFault(kind="payload", at_s=1.0, mass_kg=2.0),)


def test_config_is_frozen() -> None:
    config = load_target_config(DEPLOY / "target.virtual.yaml")
    with pytest.raises(pydantic.ValidationError):
        config.period_s = 0.5  # type: ignore[misc]  # a frozen field assigned on purpose: the refusal under test


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("period_s: -1\n", "period_s"),
        ("clock: sometimes\n", "clock"),
        ("bridge: {host: 198.51.100.5}\n", "bridge"),
        ("bus: {interface: remote, bridge_host: 203.0.113.2}\n", "bus"),
        ("faults: [{kind: payload, mass_kg: -2}]\n", "faults.0.payload.mass_kg"),
        ("faults: [{kind: earthquake}]\n", "faults.0"),
        ("plant: {substeps: 0}\n", "plant.substeps"),
        ("drives: {node_ids: [1, 1]}\n", "drives"),
        ("perod_s: 0.001\n", "perod_s"),
    ],
)
def test_bad_input_is_one_line_naming_file_and_field(tmp_path: Path, text: str, field: str) -> None:
    path = tmp_path / "target.yaml"
    path.write_text(text)
    with pytest.raises(TargetConfigError) as info:
        load_target_config(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: {field}")
    assert info.value.exit_code == 2


def test_unparsable_files_are_user_errors(tmp_path: Path) -> None:
    (tmp_path / "a.yaml").write_text("period_s: [unclosed\n")
    (tmp_path / "a.toml").write_text("period_s = \n")
    for name in ("a.yaml", "a.toml", "missing.yaml"):
        with pytest.raises(TargetConfigError, match=name):
            load_target_config(tmp_path / name)


def test_cli_reports_a_bad_config_in_one_line_with_exit_code_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "target.yaml"
    path.write_text("period_s: 0\n")
    assert hil_main(["target", "serve", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"error: {path}: period_s")


def test_fault_commands_share_the_config_schema() -> None:
    assert parse_fault({"kind": "impulse"}) == ImpulseFault(kind="impulse")  # the paper's disturbance
    assert ImpulseFault(kind="impulse").torque_nm == (1.0, 1.0, 5.0, 5.0, 10.0, 10.0)
    drive_fault = parse_fault({"kind": "drive_fault", "node_id": 3})
    assert isinstance(drive_fault, DriveFault)
    assert drive_fault.error_code == DriveFault(kind="drive_fault", node_id=3).error_code
    with pytest.raises(TargetConfigError, match="control: drive_fault.node_id"):
        parse_fault({"kind": "drive_fault", "node_id": 300}, "control")
