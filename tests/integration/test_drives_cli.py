"""``hil drives scan | check | jog`` and ``hil run`` with real vendors' dictionaries (issue 26).

(a) Against the HIL target presenting each vendor's EDS/DCF (maxon EPOS4, Nanotec C5-E) on the
    in-process virtual bus: scan finds the six drives as CiA 402 with CST and the vendor's
    identity, check passes offline and on the bus, jog moves one joint and quick-stops it.
(b) Bad input, one table: an EDS without 0x6071 or 0x6077, a drive without CST, a node answering
    with another device profile, a scaling that overflows INTEGER16 per mille at the torque
    limit, duplicate COB-IDs, an SDO init entry the EDS marks read-only: exit 2, one line naming
    the file, the node and the object, and no drive enabled.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from drivers.cia402.od import EDS_PATH
from hil_runtime.cli import main
from sim_target.testing.hil_target import target_in_process, unique_channel
from sim_target.testing.ur5 import NODE_IDS, PD_BUNDLE
from sim_target.testing.vendor_drives import EDS_DIR, VENDORS, target_profiles, vendor_bus_joints

SLOW_MACHINE = {"feedback_timeout_s": 0.2, "sdo_timeout_s": 2.0, "state_change_timeout_s": 5.0}


def runtime_yaml(path: Path, channel: str, joints: list[dict[str, Any]]) -> Path:
    path.write_text(
        yaml.safe_dump(
            {
                "robot": "ur5_paper",
                "bundle": {"path": str(PD_BUNDLE), "mode": "lmpc"},
                "bus": {
                    "transport": {"interface": "virtual", "channel": channel, "fd": True, "data_bitrate": 5_000_000},
                    "period_s": 0.001,
                    "joints": joints,
                    **SLOW_MACHINE,
                },
            }
        )
    )
    return path


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


# --- (a) the commands against the target presenting each vendor's dictionary ------------------------


@pytest.mark.parametrize("vendor", sorted(VENDORS))
def test_scan_check_jog_against_the_target_presenting_the_vendors_dictionary(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], vendor: str
) -> None:
    channel = unique_channel()
    config = runtime_yaml(tmp_path / "runtime.yaml", channel, vendor_bus_joints(vendor))
    drives = {"node_ids": list(NODE_IDS), "heartbeat_producer_ms": 50, "profiles": target_profiles(vendor)}
    with target_in_process(channel, 0.001, drives=drives) as target:
        code, out, err = run_cli(capsys, "drives", "scan", "--config", str(config), "--last", "10")
        assert code == 0, err
        assert "6 node(s) answered" in out
        rows = [line for line in out.splitlines() if re.match(r"│ [1-6] ", line)]
        assert len(rows) == 6
        vendor_id = {"maxon_epos4": "0x000000FB", "nanotec_c5": "0x0000026C"}[vendor]
        for row in rows:  # pre-operational (heartbeats heard), CiA 402, the vendor's identity, CST
            assert (
                "pre-operational" in row and "│ yes " in row and vendor_id in row and row.rstrip(" │").endswith("yes")
            )

        code, out, err = run_cli(capsys, "drives", "check", "--config", str(config))
        assert code == 0, err
        assert "6 drive(s) checked: 0 error(s)" in out
        assert "ERROR" not in out
        assert "TPDO1: 0x60410010, 0x60770010, 0x60640020, 0x606C0020" in out  # the FD layout, read back
        assert not target.drives.operation_enabled().any()

        before = target.plant.state().position_rad.copy()
        code, out, err = run_cli(
            capsys, "drives", "jog", "--config", str(config), "--joint", "shoulder_pan_joint", "--torque-nm", "0.1",
            "--seconds", "0.3",
        )  # fmt: skip
        assert code == 0, err
        assert "quick-stopped" in out
        after = target.plant.state().position_rad
        assert after[0] - before[0] > 0.02  # 0.1 N·m for 0.3 s turns the base (about 0.05 rad)
        assert abs(after[1:] - before[1:]).max() < 1e-6  # the other joints were never enabled: braked
        assert not target.drives.operation_enabled().any()  # quick-stopped at the end


def test_jog_stops_at_the_supervisors_velocity_limit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    channel = unique_channel()
    config = runtime_yaml(tmp_path / "runtime.yaml", channel, vendor_bus_joints("maxon_epos4"))
    drives = {"node_ids": list(NODE_IDS), "profiles": target_profiles("maxon_epos4")}
    with target_in_process(channel, 0.001, drives=drives) as target:
        code, _, err = run_cli(
            capsys, "drives", "jog", "--config", str(config), "--joint", "shoulder_pan_joint", "--torque-nm", "5",
            "--seconds", "2",
        )  # fmt: skip
        assert code == 3
        assert err.count("\n") == 1 and "velocity_limit: shoulder_pan_joint" in err and "quick-stopped" in err
        assert not target.drives.operation_enabled().any()


# --- (b) bad input: one table -----------------------------------------------------------------------


def _vendor(vendor: str, node: int, **drive: Any) -> Callable[[Path], list[dict[str, Any]]]:
    def make(tmp: Path) -> list[dict[str, Any]]:
        joints = vendor_bus_joints(vendor)
        joints[node - 1]["drive"].update(drive)
        return joints

    return make


def _hil_eds(name: str, edit: Callable[[str], str]) -> Callable[[Path], list[dict[str, Any]]]:
    """Node 3's drive described by a copy of the emulated drive's EDS, edited."""

    def make(tmp: Path) -> list[dict[str, Any]]:
        path = tmp / name
        path.write_text(edit(EDS_PATH.read_text()))
        joints = vendor_bus_joints("nanotec_c5")
        joints[2]["drive"] = {"eds": str(path), "rated_torque": 1000, "encoder_increments": 4096}
        return joints

    return make


def _drop(index: str) -> Callable[[str], str]:
    return lambda text: re.sub(rf"\[{index}\]\n(?:[^\[\n][^\n]*\n|\n)*", "", text)


def _default(index: str, value: str) -> Callable[[str], str]:
    return lambda text: re.sub(rf"(\[{index}\]\n[^\[]*?)DefaultValue=[^\n]*", rf"\g<1>DefaultValue={value}", text)


EPOS2 = str(EDS_DIR / "maxon_epos2_347717.eds")
# (case, the joints, command: "check" (offline), "run" or "jog", what the one line names)
BAD: list[tuple[str, Callable[[Path], list[dict[str, Any]]], str, str]] = [
    ("no_6071", _vendor("maxon_epos4", 2, eds=EPOS2), "check", "maxon_epos2_347717.eds: node 2: 0x6071:00: missing"),
    ("no_6077", _hil_eds("no6077.eds", _drop("6077")), "run", "no6077.eds: node 3: 0x6077:00: missing"),
    (
        "no_cst",
        _hil_eds("nocst.eds", _default("6502", "0x00000004")),
        "jog",
        "nocst.eds: node 3: 0x6502:00: 0x00000004: the drive does not support cyclic synchronous torque",
    ),
    (
        "overflow",
        _vendor("maxon_epos4", 4, gear_ratio=1.0),
        "check",
        "maxon_epos4_50_15.dcf: node 4: 0x6071:00: max_torque_nm 34.0 is 66293 per mille",
    ),
    (
        "duplicate_cob_id",
        _vendor("nanotec_c5", 1, sdo=[{"index": 0x1802, "sub_index": 1, "value": 0x185}]),
        "run",
        "nanotec_c5_e_2_09.eds: node 1: 0x1802:01 (SDO init): COB-ID 0x185 is also node 5's TPDO1",
    ),
    (
        "read_only_init",
        _vendor("maxon_epos4", 6, sdo=[{"index": 0x1018, "sub_index": 1, "value": 0xFB}]),
        "jog",
        "maxon_epos4_50_15.dcf: node 6: 0x1018:01: SDO init entry: the EDS marks it ro",
    ),
]


@pytest.mark.parametrize(("case", "joints", "command", "expected"), BAD, ids=[case[0] for case in BAD])
def test_bad_drive_config_is_one_line_exit_2_and_nothing_enabled(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    case: str,
    joints: Callable[[Path], list[dict[str, Any]]],
    command: str,
    expected: str,
) -> None:
    channel = unique_channel()
    bus_joints = joints(tmp_path)
    config = str(runtime_yaml(tmp_path / "runtime.yaml", channel, bus_joints))
    vendor = "maxon_epos4" if "maxon_epos4" in str(bus_joints[0]["drive"]["eds"]) else "nanotec_c5"
    argv = {
        "check": ["drives", "check", "--config", config, "--offline"],
        "run": ["run", "--config", config],
        "jog": ["drives", "jog", "--config", config, "--joint", "wrist_3_joint", "--torque-nm", "0.01"],
    }[command]
    drives = {"node_ids": list(NODE_IDS), "profiles": target_profiles(vendor)}
    with target_in_process(channel, 0.001, drives=drives) as target:  # the drives are there: none may move
        code, _, err = run_cli(capsys, *argv)
        assert not target.drives.operation_enabled().any()
        assert target.stats.steps == 0  # nothing cycled: refused before the first SYNC
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert expected in err, err


def test_a_node_answering_with_another_device_profile(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Its EDS says CiA 402; the node on the bus answers 0x1000 with profile 401 (an I/O module):
    refused at start-up, before any PDO is mapped or any drive enabled."""
    channel = unique_channel()
    config = runtime_yaml(tmp_path / "runtime.yaml", channel, vendor_bus_joints("maxon_epos4"))
    profiles = target_profiles("maxon_epos4")
    profiles[4]["device_type"] = 0x00000191
    with target_in_process(channel, 0.001, drives={"node_ids": list(NODE_IDS), "profiles": profiles}) as target:
        code, out, err = run_cli(capsys, "drives", "check", "--config", str(config))
        assert not target.drives.operation_enabled().any()
        assert target.stats.steps == 0
    assert code == 2, err
    assert err.count("\n") == 1
    assert "maxon_epos4_50_15.dcf: node 5: 0x1000:00: device type 0x00000191, profile 401, not CiA 402" in err
    code, out, err = run_cli(capsys, "drives", "scan", "--interface", "virtual", "--channel", channel)
    assert code == 0  # nothing on that channel any more: an empty table
    assert "0 node(s) answered" in out


def test_check_reads_back_the_sdo_init_list_and_refuses_a_half_reversed_drive(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An SDO init entry is written at start-up and read back by ``check``; here it sets 0x607E to
    reverse positions but not velocities, which no torque loop survives: exit 2 naming it."""
    channel = unique_channel()
    joints = vendor_bus_joints("nanotec_c5")
    joints[3]["drive"]["sdo"] = [{"index": 0x607E, "sub_index": 0, "value": 0x80}]
    config = runtime_yaml(tmp_path / "runtime.yaml", channel, joints)
    drives = {"node_ids": list(NODE_IDS), "profiles": target_profiles("nanotec_c5")}
    with target_in_process(channel, 0.001, drives=drives) as target:
        code, out, err = run_cli(capsys, "drives", "check", "--config", str(config))
        assert not target.drives.operation_enabled().any()
    assert code == 2, err
    assert "SDO init: 128" in out  # written, read back equal
    assert err.count("\n") == 1
    assert "nanotec_c5_e_2_09.eds: node 4: 0x607E:00: 0x80: the drive's own polarity (position reversed" in err


def test_jog_quick_stops_on_ctrl_c(tmp_path: Path) -> None:
    """``hil drives jog`` as a user runs it, next to ``hil target serve``: Ctrl-C while the joint
    turns quick-stops the drive before the process leaves (exit 130)."""
    import signal
    import subprocess
    import time

    from sim_target.launch import hil_command
    from sim_target.server import send_control
    from sim_target.testing.hil_target import target_process

    drives = {"node_ids": list(NODE_IDS), "profiles": target_profiles("maxon_epos4")}
    with target_process(tmp_path, 0.001, transport="ipc", drives=drives) as target:
        config = runtime_yaml(tmp_path / "runtime.yaml", "unused", vendor_bus_joints("maxon_epos4"))
        data = yaml.safe_load(config.read_text())
        data["bus"]["transport"].update({"interface": "ipc", "channel": str(target.ipc_dir)})
        config.write_text(yaml.safe_dump(data))
        argv = ["drives", "jog", "--config", str(config), "--joint", "shoulder_pan_joint", "--torque-nm", "0.01"]
        process = subprocess.Popen(
            hil_command(*argv, "--seconds", "30"),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # a shell's child may ignore it
        )
        try:
            deadline = time.monotonic() + 120
            while not send_control(target.control_socket, {"kind": "status"})["operation_enabled"][0]:
                assert process.poll() is None, process.communicate()[1]
                assert time.monotonic() < deadline, "the jog never enabled its drive"
                time.sleep(0.05)
            time.sleep(0.3)  # turning now
            process.send_signal(signal.SIGINT)
            _, err = process.communicate(timeout=60)
        finally:
            if process.poll() is None:
                process.kill()
                process.communicate()
        status = send_control(target.control_socket, {"kind": "status"})
    assert process.returncode == 130, err
    assert "Traceback" not in err
    assert status["operation_enabled"] == [False] * 6  # quick-stopped before the process left
