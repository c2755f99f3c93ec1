"""Captures and records through the installed ``hil`` and python-can's own tools: a capture
replayed onto the ipc bus by ``python -m can.player``; bad record paths, captures and records
are one line, exit 2 (one table, run like tests/integration/test_cli_bad_inputs.py)."""

from __future__ import annotations

import subprocess
import sys
import uuid
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import can
import pytest

from drivers.capture import CanCapture
from drivers.cia402 import frames as fr
from tests.integration.test_cli_bad_inputs import Case, _run_case

ROOT = Path(__file__).resolve().parents[2]
RUNTIME_YAML = (ROOT / "deploy" / "runtime.ipc.yaml").read_text()
YAML = b"robot: ur5_paper\nperiod_s: 0.001\n"
# The ipc deploy config with its bundle found from anywhere (its path is relative to deploy/).
RUNTIME_ABS = RUNTIME_YAML.replace("../models/bundles", str(ROOT / "models" / "bundles"))


def _capture(path: Path, count: int) -> list[can.Message]:
    frames = [
        can.Message(arbitration_id=0x201 + k % 6, data=fr.encode_rpdo(0x000F, k - 100), is_extended_id=False)
        for k in range(count)
    ]
    capture = CanCapture(path)
    for msg in frames:
        capture.tap(msg, False)
    capture.close()
    return frames


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the ipc bus is Linux only")
@pytest.mark.parametrize("suffix", [".blf", ".log"])
def test_can_player_replays_a_capture_onto_the_ipc_bus(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"run{suffix}"
    sent = _capture(path, 120)
    channel = tmp_path / f"bus-{uuid.uuid4().hex[:6]}"
    with can.Bus(interface="ipc", channel=str(channel)) as listener:
        done = subprocess.run(
            [sys.executable, "-m", "can.player", "-i", "ipc", "-c", str(channel), "--ignore-timestamps", str(path)],
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert done.returncode == 0, done.stderr
        received = []
        while (msg := listener.recv(2.0)) is not None:
            received.append(msg)
    assert [(m.arbitration_id, bytes(m.data)) for m in received] == [(m.arbitration_id, bytes(m.data)) for m in sent]


def _bytes_of_capture(suffix: str, cut: int) -> bytes:
    path = Path(f"/tmp/hil-formats-{uuid.uuid4().hex[:8]}{suffix}")
    try:
        _capture(path, 30)
        data = path.read_bytes()
    finally:
        path.unlink(missing_ok=True)
    return data[: len(data) - cut]


CASES: list[Case] = [
    (
        "record-suffix",
        ["run", "--config", "{tmp}/rt.yaml", "--record", "{tmp}/run.bag"],
        {"rt.yaml": RUNTIME_YAML},
        ["--record {tmp}/run.bag", "unknown record format '.bag'"],
    ),
    (
        "record-unwritable",
        ["run", "--config", "{tmp}/rt.yaml", "--record", "{tmp}/f/run.mcap"],
        {"rt.yaml": RUNTIME_YAML, "f": "a file"},
        ["--record {tmp}/f", "a file is in the way"],
    ),
    (
        "can-log-suffix",
        ["run", "--config", "{tmp}/rt.yaml", "--can-log", "{tmp}/run.pcap"],
        {"rt.yaml": RUNTIME_YAML},
        ["--can-log {tmp}/run.pcap", "unknown capture format '.pcap'"],
    ),
    (
        "can-log-unwritable",
        ["target", "serve", "--config", "{tmp}/t.yaml", "--can-log", "{tmp}/none/run.blf"],
        {"t.yaml": "robot: ur5_paper\n"},
        ["--can-log {tmp}/none/run.blf", "no directory"],
    ),
    (
        "mcap-urdf-of-another-arm",
        ["run", "--config", "{tmp}/rt.yaml", "--record", "{tmp}/run.mcap", "--urdf", "{tmp}/arm.urdf"],
        {"rt.yaml": RUNTIME_ABS, "arm.urdf": "<robot name='other'/>"},
        ["--urdf {tmp}/arm.urdf", "sha256 differs from the bundle's robot.urdf_sha256"],
    ),
    (
        "telemetry-record-suffix",
        ["telemetry", "record", "--out", "{tmp}/run.bag"],
        {},
        ["--out {tmp}/run.bag", "unknown record format"],
    ),
    (
        "decode-truncated-blf",
        ["bus", "decode", "{tmp}/c.blf"],
        {"c.blf": _bytes_of_capture(".blf", 7)},
        ["{tmp}/c.blf", "truncated Vector BLF capture"],
    ),
    (
        "decode-truncated-log",
        ["bus", "decode", "{tmp}/c.log"],
        {"c.log": _bytes_of_capture(".log", 4)},
        ["{tmp}/c.log", "truncated candump -L capture"],
    ),
    (
        "decode-truncated-asc",
        ["bus", "decode", "{tmp}/c.asc"],
        {"c.asc": _bytes_of_capture(".asc", 30)},
        ["{tmp}/c.asc", "truncated Vector ASC capture"],
    ),
    ("decode-foreign-blf", ["bus", "decode", "{tmp}/c.blf"], {"c.blf": YAML}, ["{tmp}/c.blf", "not a Vector BLF"]),
    ("decode-foreign-log", ["bus", "decode", "{tmp}/c.log"], {"c.log": YAML}, ["{tmp}/c.log", "candump"]),
    ("decode-foreign-csv", ["bus", "decode", "{tmp}/c.csv"], {"c.csv": YAML}, ["{tmp}/c.csv", "not a python-can CSV"]),
    (
        "decode-blf-as-log",
        ["bus", "decode", "{tmp}/c.log"],
        {"c.log": _bytes_of_capture(".blf", 0)},
        ["{tmp}/c.log", "not a candump -L capture"],
    ),
    ("decode-suffix", ["bus", "decode", "{tmp}/c.pcap"], {"c.pcap": b"x"}, ["{tmp}/c.pcap", "unknown capture format"]),
    ("decode-missing", ["bus", "decode", "{tmp}/none.blf"], {}, ["{tmp}/none.blf", "no such file"]),
    (
        "plot-foreign-mcap",
        ["telemetry", "plot", "{tmp}/r.mcap"],
        {"r.mcap": YAML},
        ["{tmp}/r.mcap", "not a readable MCAP record"],
    ),
    (
        "plot-truncated-mcap",
        ["telemetry", "plot", "{tmp}/r.mcap"],
        {"r.mcap": b"\x89MCAP0\r\n\x01\x02"},
        ["{tmp}/r.mcap", "not a readable MCAP record"],
    ),
    (
        "plot-capture-as-mcap",
        ["telemetry", "plot", "{tmp}/r.mcap"],
        {"r.mcap": _bytes_of_capture(".blf", 0)},
        ["{tmp}/r.mcap", "invalid magic"],
    ),
]


def test_bad_record_paths_captures_and_records_are_one_line_exit_2(tmp_path: Path, hil_command: list[str]) -> None:
    failures = []
    with ThreadPoolExecutor(max_workers=3) as pool:
        results = list(pool.map(lambda case: _run_case(hil_command, case, tmp_path), CASES))
    for name, code, stderr, expected in results:
        lines = [line for line in stderr.splitlines() if line.strip()]
        if code != 2 or len(lines) != 1 or not all(e in lines[0] for e in expected) or "Traceback" in stderr:
            failures.append(f"{name}: exit {code}, stderr {stderr!r}, expected {expected}")
    assert not failures, "\n".join(failures)
