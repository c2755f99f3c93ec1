"""Bad realism profiles through the INSTALLED ``hil`` entry point (issue 23): exit code 2, exactly one
line on stderr naming the file and the field, no traceback, on every command that takes a profile.

One table: (case id, argv, profile text, what the line must contain); ``{tmp}`` is the temporary
directory, the profile is written to ``{tmp}/p.yaml``.
"""

from __future__ import annotations

import os
from pathlib import Path
from subprocess import run

import pytest

EXPERIMENT = ["experiment", "--laws", "pd", "--modes", "fb", "--timing-cycles", "5", "--no-plots", "--out", "{tmp}/o"]
HIL_EXPERIMENT = [*EXPERIMENT[:-2], "--plant", "hil", "--out", "{tmp}/o"]
DEMO = ["demo", "--headless", "--law", "pd", "--mode", "fb", "--duration", "0.1", "--out", "{tmp}/o"]
TARGET = ["target", "serve", "--config", "{tmp}/t.yaml"]
PROFILE = "{tmp}/p.yaml"
TARGET_CONFIG = (
    "robot: ur5_paper\nbus: {interface: virtual, channel: rl, fd: true, data_bitrate: 5000000}\nrealism: p.yaml\n"
)

CASES: list[tuple[str, list[str], str, list[str]]] = [
    (
        "negative",
        [*EXPERIMENT, "--realism", PROFILE],
        "sensing: {encoder_noise_rad: -1e-5}\n",
        ["sensing.encoder_noise_rad"],
    ),
    ("nan", [*EXPERIMENT, "--realism", PROFILE], "plant: {coulomb_friction_nm: .nan}\n", ["plant.coulomb_friction_nm"]),
    (
        "unknown field",
        [*EXPERIMENT, "--realism", PROFILE],
        "actuation: {torque_lag_s: 0.001}\n",
        ["actuation.torque_lag_s"],
    ),
    (
        "wrong length",
        [*EXPERIMENT, "--realism", PROFILE],
        "plant: {viscous_friction_nm_s_per_rad: [1, 2]}\n",
        ["plant.viscous_friction_nm_s_per_rad", "6"],
    ),
    (
        # an explicit per-joint list is for one joint count: the 7-joint Panda refuses a 6-joint list
        "wrong length (panda)",
        [*EXPERIMENT, "--robot", "panda", "--realism", PROFILE],
        "plant: {coulomb_friction_nm: [1.5, 1.5, 1.0, 0.3, 0.3, 0.3]}\n",
        ["plant.coulomb_friction_nm", "7"],
    ),
    (
        # the simulator's physics step is period / substeps = 0.5 ms: Nyquist 1 kHz
        "bandwidth above nyquist (sim)",
        [*EXPERIMENT, "--realism", PROFILE],
        "actuation: {torque_bandwidth_hz: 1500}\n",
        ["actuation.torque_bandwidth_hz", "Nyquist"],
    ),
    (
        "bandwidth above nyquist (hil)",
        [*HIL_EXPERIMENT, "--target-substeps", "1", "--realism", PROFILE],
        "actuation: {torque_bandwidth_hz: 900}\n",
        ["actuation.torque_bandwidth_hz", "Nyquist"],
    ),
    ("demo", [*DEMO, "--realism", PROFILE], "sensing: {delay_periods: -1}\n", ["sensing.delay_periods"]),
    ("unknown profile", [*EXPERIMENT, "--realism", "realistc"], "", ["--realism", "realistc"]),
    (
        "target config",
        TARGET,
        "sensing: {velocity: differenced}\n",
        ["sensing.velocity"],
    ),
]


@pytest.mark.parametrize(("name", "argv", "profile", "expected"), CASES, ids=[c[0] for c in CASES])
def test_bad_profile_one_line_exit_2(
    tmp_path: Path, name: str, argv: list[str], profile: str, expected: list[str]
) -> None:
    (tmp_path / "p.yaml").write_text(profile)
    (tmp_path / "t.yaml").write_text(TARGET_CONFIG)
    args = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    env = {**os.environ, "COLUMNS": "400"}
    result = run(["hil", *args], capture_output=True, text=True, timeout=120, env=env)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2, (result.returncode, result.stderr)
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for part in expected:
        assert part in lines[0], lines[0]
    if profile:
        assert "p.yaml" in lines[0]
    assert not (tmp_path / "o").exists()  # refused before any work
