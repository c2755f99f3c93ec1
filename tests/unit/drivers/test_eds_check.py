"""Offline checks of drives against their own EDS/DCF (drivers/eds_check.py): real vendors'
dictionaries pass or fail for their real reasons, the emulated drive's own EDS passes the same
checks, and each bad input is one line naming the file, the node and the object."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

from drivers.cia402.od import EDS_PATH
from drivers.config import parse_drive_bus_config
from drivers.drive_spec import spec_scale
from drivers.eds_check import check_bus, errors, raise_first_error
from drivers.errors import DriveConfigError
from sim_target.testing.ur5 import bus_joints
from sim_target.testing.vendor_drives import EDS_DIR, VENDORS, vendor_bus_joints

CLASSICAL = {"interface": "virtual", "channel": "unused"}
FD = {**CLASSICAL, "fd": True, "data_bitrate": 5_000_000}


def bus(joints: list[dict[str, Any]], transport: dict[str, Any] | None = None, **extra: Any) -> Any:
    return parse_drive_bus_config({"transport": transport or FD, "period_s": 0.001, "joints": joints, **extra})


def without_section(text: str, index: str) -> str:
    """The EDS text without the object ``index`` (and its sub-index sections)."""
    return re.sub(rf"\[{index}(sub[0-9A-Fa-f]+)?\]\n(?:[^\[\n][^\n]*\n|\n)*", "", text)


def with_default(text: str, index: str, value: str) -> str:
    return re.sub(rf"(\[{index}\]\n(?:[^\[]*?))DefaultValue=[^\n]*", rf"\g<1>DefaultValue={value}", text, count=1)


def hil_eds_variant(tmp_path: Path, name: str, edit: Any) -> Path:
    path = tmp_path / name
    path.write_text(edit(EDS_PATH.read_text()))
    return path


def test_the_emulated_drives_eds_passes_the_same_checks() -> None:
    for transport, period_s in ((CLASSICAL, 0.004), (FD, 0.001)):
        assert errors(check_bus(bus(bus_joints(), transport, period_s=period_s))) == []


@pytest.mark.parametrize("vendor", sorted(VENDORS))
def test_each_vendor_drive_set_passes_offline(vendor: str) -> None:
    findings = check_bus(bus(vendor_bus_joints(vendor)))
    assert errors(findings) == [], [f.line() for f in findings]


def test_a_dcf_used_for_another_node_is_flagged() -> None:
    lines = [f.line() for f in check_bus(bus(vendor_bus_joints("maxon_epos4")))]
    assert any("node 2: -: DCF commissioned for node 1" in line for line in lines)


def one_drive(drive: dict[str, Any], max_torque_nm: float = 34.0) -> list[dict[str, Any]]:
    return [{"name": "j", "node_id": 5, "max_torque_nm": max_torque_nm, "drive": drive}]


def _epos2(tmp_path: Path) -> dict[str, Any]:
    return {"eds": str(EDS_DIR / "maxon_epos2_347717.eds"), "rated_torque": 100, "encoder_increments": 4096}


def _no_6077(tmp_path: Path) -> dict[str, Any]:
    path = hil_eds_variant(tmp_path, "no6077.eds", lambda t: without_section(t, "6077"))
    return {"eds": str(path), "rated_torque": 1000, "encoder_increments": 4096}


def _no_cst(tmp_path: Path) -> dict[str, Any]:
    path = hil_eds_variant(tmp_path, "nocst.eds", lambda t: with_default(t, "6502", "0x00000001"))
    return {"eds": str(path), "rated_torque": 1000, "encoder_increments": 4096}


def _other_profile(tmp_path: Path) -> dict[str, Any]:
    path = hil_eds_variant(tmp_path, "io.eds", lambda t: with_default(t, "1000", "0x00000191"))
    return {"eds": str(path), "rated_torque": 1000, "encoder_increments": 4096}


def _overflow(tmp_path: Path) -> dict[str, Any]:
    # The EPOS4's own 0x6076 (512871 µN·m) without a gear: 34 N·m is 66,294 per mille.
    return {"eds": str(EDS_DIR / "maxon_epos4_50_15.dcf"), "rated_torque_unit_nm": 1e-6, "encoder_increments": 4096}


def _read_only_init(tmp_path: Path) -> dict[str, Any]:
    return {
        "eds": str(EDS_DIR / "nanotec_c5_e_2_09.eds"),
        "rated_torque": 440,
        "gear_ratio": 100,
        "sdo": [{"index": 0x6064, "sub_index": 0, "value": 0}],
    }


def _init_out_of_range(tmp_path: Path) -> dict[str, Any]:
    return {
        "eds": str(EDS_DIR / "maxon_epos4_50_15.dcf"),
        "rated_torque_unit_nm": 1e-6,
        "gear_ratio": 100,
        "encoder_increments": 4096,
        "sdo": [{"index": 0x1600, "sub_index": 0, "value": 2}],  # owned by the runtime
    }


def _missing_6076(tmp_path: Path) -> dict[str, Any]:
    # The C5-E has no 0x6076: its rated torque must be given.
    return {"eds": str(EDS_DIR / "nanotec_c5_e_2_09.eds"), "gear_ratio": 100}


BAD = [
    (_epos2, "maxon_epos2_347717.eds: node 5: 0x6071:00: missing from the EDS"),
    (_no_6077, "no6077.eds: node 5: 0x6077:00: missing from the EDS"),
    (_no_cst, "nocst.eds: node 5: 0x6502:00: 0x00000001: the drive does not support cyclic synchronous torque"),
    (_other_profile, "io.eds: node 5: 0x1000:00: device profile 401, not CiA 402"),
    (_overflow, "maxon_epos4_50_15.dcf: node 5: 0x6071:00: max_torque_nm 34.0 is 66293 per mille"),
    (_read_only_init, "nanotec_c5_e_2_09.eds: node 5: 0x6064:00: SDO init entry: the EDS marks it ro"),
    (_init_out_of_range, "maxon_epos4_50_15.dcf: node 5: 0x1600:00: written by the runtime itself"),
    (_missing_6076, "nanotec_c5_e_2_09.eds: node 5: 0x6076:00: missing from the EDS: give joints.0.drive.rated_torque"),
]


@pytest.mark.parametrize(("make", "expected"), BAD, ids=[make.__name__.strip("_") for make, _ in BAD])
def test_bad_drive_is_one_line_naming_file_node_and_object(tmp_path: Path, make: Any, expected: str) -> None:
    config = bus(one_drive(make(tmp_path)))
    with pytest.raises(DriveConfigError) as info:
        raise_first_error(check_bus(config))
    message = str(info.value)
    assert "\n" not in message
    assert expected in message, message


def test_duplicate_cob_id_from_an_sdo_init_entry() -> None:
    joints = vendor_bus_joints("nanotec_c5")
    # Node 1's TPDO3 moved onto node 2's TPDO1 identifier: two senders on 0x182.
    joints[0]["drive"]["sdo"] = [{"index": 0x1802, "sub_index": 1, "value": 0x182}]
    with pytest.raises(
        DriveConfigError, match=r"c5_e_2_09.eds: node 1: 0x1802:01 \(SDO init\): COB-ID 0x182 is also node 2's TPDO1"
    ):
        raise_first_error(check_bus(bus(joints)))


def test_scaling_from_spec_and_drive_values() -> None:
    config = bus(vendor_bus_joints("maxon_epos4"))
    spec = config.joints[1].drive
    assert spec is not None
    scale = spec_scale(spec, {"rated_torque": 512_871})
    assert scale.nm_per_permille == pytest.approx(-512_871e-6 * 160 / 1000)  # polarity -1
    assert scale.counts_per_rad == pytest.approx(-3200 * 160 / (2 * 3.141592653589793))


DEPLOY_DRIVES = Path(__file__).resolve().parents[3] / "deploy" / "drives"


@pytest.mark.parametrize("config", sorted(DEPLOY_DRIVES.glob("*.runtime.yaml")), ids=lambda p: p.name)
def test_the_shipped_vendor_configs_pass_their_eds_checks(config: Path) -> None:
    from hil_runtime.config import load_runtime_config
    from sim_target.config import load_target_config

    runtime = load_runtime_config(config)
    assert all(joint.drive is not None and joint.drive.eds.is_file() for joint in runtime.bus.joints)
    assert errors(check_bus(runtime.bus)) == []
    target = load_target_config(config.with_name(config.name.replace(".runtime.", ".target.")))
    assert target.drives.profiles is not None and all(p.eds.is_file() for p in target.drives.profiles)
    assert target.bus.channel == runtime.bus.transport.channel
