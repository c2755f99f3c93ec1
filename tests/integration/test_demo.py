"""``hil demo`` end to end through the installed entry point (issue 16): the pybullet target and
``hil run`` as two processes over the ipc bus, telemetry over Zenoh on loopback, then a clean stop.

Checked: the outputs (the telemetry record with its schema, the runtime's record, the plot, the
scores beside the simulation's, the loop's timing); that the drives were quick-stopped; and that
nothing is left running: no child process, no socket, no private directory. Ctrl-C in the middle
of the run stops everything the same way (exit 130, no output file).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from models.robots import load_robot

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the ipc bus is Linux only")

DURATION_S = 2.5  # past C1's disturbance at 2 s


@pytest.fixture
def private_tmp() -> Iterator[Path]:
    """A short TMPDIR for the demo alone (its bus sockets live there: Unix paths are short)."""
    path = Path(tempfile.mkdtemp(prefix="hdt-", dir="/tmp"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


def _processes_mentioning(text: str) -> list[str]:
    """Processes whose command line names ``text`` (the demo's children name their private directory)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if text in cmdline:
            found.append(f"{entry.name}: {cmdline.strip()}")
    return found


def _assert_nothing_left(private: Path, pids: list[int]) -> None:
    deadline = time.monotonic() + 5.0
    while _processes_mentioning(str(private)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _processes_mentioning(str(private)) == []
    for pid in pids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
    # (Only the demo's own directory: a library of the simulator keeps a small file in TMPDIR.)
    assert list(private.glob("hil-demo-*")) == [], (
        "the demo's private directory (bus and control sockets) was left behind"
    )


def test_hil_demo_headless_end_to_end(tmp_path: Path, private_tmp: Path, hil_command: list[str]) -> None:
    out = tmp_path / "demo"
    started = time.monotonic()
    run = subprocess.run(
        [*hil_command, "demo", "--headless", "--duration", str(DURATION_S), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
        env={**os.environ, "TMPDIR": str(private_tmp)},
    )
    wall_s = time.monotonic() - started
    assert run.returncode == 0, run.stdout + run.stderr
    assert "Traceback" not in run.stderr
    results = json.loads((out / "results.json").read_text())

    # Nothing left running, no socket, no directory.
    pids = [results["processes"][name]["pid"] for name in ("target", "runtime")]
    _assert_nothing_left(private_tmp, pids)
    stop = results["shutdown"]
    assert stop["runtime_exit_code"] == 0 and stop["target_exit_code"] == 0
    assert stop["drives_operation_enabled_after_stop"] == [False] * 6  # quick-stopped by the SIGTERM
    assert stop["ipc_sockets_left"] == [] and stop["control_sockets_left"] == [] and stop["processes_alive"] == []
    assert stop["work_dir_removed"] and results["work_dir"].startswith(str(private_tmp))
    assert "state FINALIZED" in (out / "logs" / "runtime.log").read_text()

    # The run: the whole (shortened) condition, lock-stepped, no fault.
    steps = round(DURATION_S / 1e-3)
    assert results["fault"] is None and results["coverage"]["complete"]
    with np.load(out / "runtime_record.npz") as data:
        record = {k: data[k] for k in data.files}
    assert record["q"].shape[0] >= steps and record["q"].shape[1] == 6
    np.testing.assert_allclose(record["t_s"][:steps], np.arange(steps) * 1e-3, atol=1e-9)

    # The telemetry record: schema embedded, every state received, equal to the runtime's own rows.
    with np.load(out / "run.npz") as data:
        telemetry = {k: data[k] for k in data.files}
    schema = json.loads(str(telemetry["schema"]))
    assert schema["schema"] == "hil-telemetry" and schema["robot"] == "ur5_paper"
    state_fields = [f["name"] for f in schema["payloads"]["state"]["fields"]]
    assert state_fields == "fallback compute_s q qd q_ref qd_ref tau tau_fb".split()
    assert list(telemetry["joints"]) == list(load_robot("ur5_paper").joint_names)
    assert results["telemetry"]["missing"] == 0 and results["telemetry"]["samples"] >= steps
    assert results["telemetry"]["max_abs_q_diff_vs_record_rad"] == 0.0

    # Scores beside the simulation's: the same bundle on the same condition tracks alike.
    scores = results["scores"]
    assert scores["within_limits"] == {"hil": True, "sim": True}
    assert abs(scores["relative"]["rmse"]) < 0.10, scores
    assert scores["trajectory_rms_diff_deg"] < 0.05, scores
    assert (out / "tracking_error.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = (out / "summary.md").read_text()
    assert "| RMSE (deg) |" in summary and "composite" in summary

    # The loop's figures, from the runtime's own stats over the run.
    timing = results["timing"]
    assert timing["cycles"] >= steps - 1 and timing["rate_hz"] > 0
    for name in ("period_us", "compute_us"):
        figures = timing[name]
        assert 0 < figures["median"] <= figures["p99"] <= figures["max"], timing
    assert timing["telemetry_dropped"] == 0
    assert "wrote" in run.stdout and "no process or socket left" in run.stdout
    print(
        f"hil demo --headless --duration {DURATION_S}: {wall_s:.1f} s wall, {results['wall_s']}, "
        f"{timing['rate_hz']} Hz, load {results['load_average']}"
    )


def test_hil_demo_ctrl_c_during_the_run_stops_everything(
    tmp_path: Path, private_tmp: Path, hil_command: list[str]
) -> None:
    out = tmp_path / "demo"
    process = subprocess.Popen(
        [*hil_command, "demo", "--headless", "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "TMPDIR": str(private_tmp)},
        start_new_session=True,
    )
    try:
        # Wait until the daemon is ACTIVE (the demo says "running"), then Ctrl-C.
        assert process.stderr is not None
        lines = []
        for line in process.stderr:
            lines.append(line)
            if "hil demo: running" in line:
                break
        else:
            pytest.fail("the demo never reached its run: " + "".join(lines))
        time.sleep(0.5)
        os.kill(process.pid, signal.SIGINT)
        _, rest = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    err = "".join(lines) + rest
    assert process.returncode == 130, err
    assert "Traceback" not in err
    assert "hil run exit 0, drives stopped (Operation Enabled off)" in err, err
    assert "no process, socket or directory left" in err
    _assert_nothing_left(private_tmp, [])
    assert not (out / "results.json").exists()


@pytest.mark.parametrize(
    ("args", "env", "message"),
    [
        (["--gui"], {"DISPLAY": ""}, "--gui: no display"),
        (["--law", "lqr"], {}, "--law: unknown 'lqr'"),
        (["--condition", "C9"], {}, "--condition: unknown 'C9'"),
        (["--duration", "nan"], {}, "--duration: must be"),
        (["--mode", "hmpc"], {}, "--mode: unknown 'hmpc'"),
        (["--out", "/proc/hil-demo-out"], {}, "--out /proc/hil-demo-out: cannot create the directory"),
    ],
)
def test_hil_demo_refuses_bad_input_before_starting_anything(
    tmp_path: Path, private_tmp: Path, args: list[str], env: dict[str, str], message: str, hil_command: list[str]
) -> None:
    run = subprocess.run(
        [*hil_command, "demo", "--headless", "--out", str(tmp_path / "demo"), *args],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        env={**os.environ, "TMPDIR": str(private_tmp), **env},
    )
    assert run.returncode == 2, run.stderr
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0], run.stderr
    assert list(private_tmp.glob("hil-demo-*")) == [] and not (tmp_path / "demo").exists()
