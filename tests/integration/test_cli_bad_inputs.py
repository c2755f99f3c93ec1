"""Every bad input of issue 9 through the INSTALLED ``hil`` entry point, as a user meets it:
exit code 2, exactly one line on stderr, naming the file (or option) and the field, no traceback.

One table: (case id, argv, files to create, what the line must contain). Files are written into a
temporary directory; ``{tmp}`` in argv and expectations is replaced by its path.
"""

from __future__ import annotations

import json
import os
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from subprocess import run

ROOT = Path(__file__).resolve().parents[2]
UR5_URDF = (ROOT / "models" / "robots" / "data" / "ur5_paper.urdf").read_text()
PD_BUNDLE = ROOT / "models" / "bundles" / "ur5_paper" / "pd"
SIX = "[0, 0, 0, 0, 0, 0]"
FD = "bus: {interface: virtual, channel: x, fd: true, data_bitrate: 5000000}\n"


def _condition(extra: str) -> str:
    return f"conditions:\n  - name: A\n    amplitude_rad: {SIX}\n{extra}"


def _urdf(pattern: str, replacement: str) -> str:
    text, count = re.subn(pattern, replacement, UR5_URDF, count=1, flags=re.DOTALL)
    assert count == 1, pattern
    return text


def _manifest(change) -> str:  # type: ignore[no-untyped-def]
    manifest = json.loads((PD_BUNDLE / "manifest.json").read_text())
    change(manifest)
    return json.dumps(manifest)


EXPERIMENT = [
    "experiment",
    "--laws",
    "pd",
    "--modes",
    "fb",
    "--timing-cycles",
    "5",
    "--no-plots",
    "--no-trajectories",
    "--out",
    "{tmp}/out",
]
LMPC = [
    "experiment",
    "--laws",
    "pd",
    "--modes",
    "lmpc",
    "--timing-cycles",
    "5",
    "--no-plots",
    "--no-trajectories",
    "--out",
    "{tmp}/out",
    "--lmpc-bundles",
    "{tmp}/bundles",
]

# (id, argv, {relative file: text or bytes}, substrings of the one stderr line)
CASES: list[tuple[str, list[str], dict[str, str | bytes], list[str]]] = [
    # conditions
    (
        "payload<0",
        [*EXPERIMENT, "--conditions", "{tmp}/c.yaml"],
        {"c.yaml": _condition("    mismatch: {payload_kg: -1}\n")},
        ["c.yaml", "mismatch.payload_kg: must be >= 0"],
    ),
    (
        "frequency<0",
        [*EXPERIMENT, "--conditions", "{tmp}/c.yaml"],
        {"c.yaml": _condition("    frequency_hz: -0.1\n")},
        ["c.yaml", "frequency_hz[0]: must be >= 0"],
    ),
    (
        "disturbance-late",
        [*EXPERIMENT, "--conditions", "{tmp}/c.yaml"],
        {"c.yaml": _condition("    duration_s: 1\n    disturbance: {time_s: 2}\n")},
        ["c.yaml", "disturbance.time_s"],
    ),
    (
        "inertia_scale=0",
        [*EXPERIMENT, "--conditions", "{tmp}/c.yaml"],
        {"c.yaml": _condition("    mismatch: {inertia_scale: 0}\n")},
        ["c.yaml", "inertia_scale[0]: must be > 0"],
    ),
    (
        "conditions-binary",
        [*EXPERIMENT, "--conditions", "{tmp}/c.yaml"],
        {"c.yaml": bytes(range(256))},
        ["c.yaml", "not a UTF-8 text file"],
    ),
    ("conditions-empty", [*EXPERIMENT, "--conditions", "{tmp}/c.yaml"], {"c.yaml": ""}, ["c.yaml", "empty file"]),
    (
        "conditions-nan",
        [*EXPERIMENT, "--conditions", "{tmp}/c.yaml"],
        {"c.yaml": "conditions:\n  - name: A\n    amplitude_rad: [.nan, 0, 0, 0, 0, 0]\n"},
        ["c.yaml", "amplitude_rad[0]: not finite"],
    ),
    # options
    ("timing-cycles=0", ["experiment", "--timing-cycles", "0"], {}, ["--timing-cycles", "positive"]),
    ("timing-cycles<0", ["experiment", "--timing-cycles", "-3"], {}, ["--timing-cycles", "positive"]),
    ("period_s=0", ["experiment", "--period-s", "0"], {}, ["--period-s", "positive"]),
    ("unknown-option", ["experiment", "--colour", "red"], {}, ["No such option: --colour"]),
    ("unknown-robot", ["experiment", "--robot", "r2d2"], {}, ["robot: unknown name 'r2d2'", "ur5_paper"]),
    # --out
    ("out-file-in-the-way", ["experiment", "--out", "{tmp}/f"], {"f": "x"}, ["--out {tmp}/f: a file is in the way"]),
    (
        "out-parent-is-a-file",
        ["experiment", "--out", "{tmp}/f/sub/out"],
        {"f": "x"},
        ["{tmp}/f is a file, not a directory"],
    ),
    (
        "out-read-only-fs",
        ["experiment", "--out", "/proc/hil-out"],
        {},
        ["--out /proc/hil-out: cannot create the directory"],
    ),
    # URDF
    (
        "urdf-no-limit",
        [*EXPERIMENT, "--robot", "{tmp}/arm.urdf"],
        {"arm.urdf": _urdf(r"<limit [^>]*/>", "")},
        ["arm.urdf", "joint 'shoulder_pan_joint' <limit>: missing"],
    ),
    (
        "urdf-prismatic",
        [*EXPERIMENT, "--robot", "{tmp}/arm.urdf"],
        {"arm.urdf": _urdf(r'(<joint name="elbow_joint" type=)"revolute"', r'\1"prismatic"')},
        ["arm.urdf", "'elbow_joint' type 'prismatic'"],
    ),
    (
        "urdf-negative-inertia",
        [*EXPERIMENT, "--robot", "{tmp}/arm.urdf"],
        {"arm.urdf": _urdf(r'ixx="', 'ixx="-')},
        ["arm.urdf", "<inertia> ixx: negative"],
    ),
    (
        "urdf-binary",
        [*EXPERIMENT, "--robot", "{tmp}/arm.urdf"],
        {"arm.urdf": b"\x89PNG\r\n\x1a\n\x00\x00"},
        ["arm.urdf", "not valid XML"],
    ),
    # target configs
    (
        "target-q0-outside",
        ["target", "serve", "--config", "{tmp}/t.yaml"],
        {"t.yaml": FD + "plant: {initial_position_rad: [0, 0, 3.0, 0, 0, 0]}\n"},
        ["t.yaml", "plant.initial_position_rad[2]", "outside"],
    ),
    (
        "target-urdf-negative-mass",
        ["target", "serve", "--config", "{tmp}/t.yaml"],
        {"t.yaml": FD + "urdf: arm.urdf\n", "arm.urdf": _urdf(r'<mass value="', '<mass value="-')},
        ["t.yaml", "arm.urdf", "<mass> value: negative"],
    ),
    (
        "target-urdf-negative-inertia",
        ["target", "serve", "--config", "{tmp}/t.yaml"],
        {"t.yaml": FD + "urdf: arm.urdf\n", "arm.urdf": _urdf(r'izz="', 'izz="-')},
        ["t.yaml", "arm.urdf", "<inertia> izz: negative"],
    ),
    (
        "target-canfd-5khz",
        ["target", "serve", "--config", "{tmp}/t.yaml"],
        {"t.yaml": "period_s: 0.0002\nbus: {interface: virtual, fd: true, data_bitrate: 5000000}\n"},
        ["t.yaml", "bus:", "above the 85% limit"],
    ),
    (
        "target-classical-500hz",
        ["target", "serve", "--config", "{tmp}/t.yaml"],
        {"t.yaml": "period_s: 0.002\nbus: {interface: virtual}\n"},
        ["t.yaml", "classical CAN", "101.4% load"],
    ),
    ("target-empty", ["target", "serve", "--config", "{tmp}/t.yaml"], {"t.yaml": ""}, ["t.yaml", "empty file"]),
    (
        "target-binary",
        ["target", "serve", "--config", "{tmp}/t.yaml"],
        {"t.yaml": bytes(range(256))},
        ["t.yaml", "not a UTF-8 text file"],
    ),
    (
        "target-nan",
        ["target", "serve", "--config", "{tmp}/t.yaml"],
        {"t.yaml": FD + "period_s: .nan\n"},
        ["t.yaml", "period_s: Input should be a finite number"],
    ),
    # inject (schema checked before the socket is even tried)
    (
        "inject-negative-inertia",
        [
            "target",
            "inject",
            "--socket",
            "{tmp}/none.sock",
            '{"kind": "payload", "mass_kg": 1, "inertia_kg_m2": [-1, 0, 0]}',
        ],
        {},
        ["inject: payload.inertia_kg_m2.0: Input should be greater than or equal to 0"],
    ),
    (
        "inject-infinite",
        ["target", "inject", "--socket", "{tmp}/none.sock", '{"kind": "encoder_noise", "position_rad": Infinity}'],
        {},
        ["inject: encoder_noise.position_rad: Input should be a finite number"],
    ),
    (
        "inject-no-target",
        ["target", "inject", "--socket", "{tmp}/none.sock", '{"kind": "status"}'],
        {},
        ["{tmp}/none.sock: cannot reach the target"],
    ),
    # bundles
    (
        "bundle-dir-without-manifest",
        LMPC,
        {"bundles/empty.txt": ""},
        ["bundle directory {tmp}/bundles: no bundle for law 'pd'"],
    ),
    (
        "bundle-torque-edited",
        LMPC,
        {
            "bundles/pd/manifest.json": _manifest(lambda m: m["limits"].__setitem__("torque_nm", [1.0] * 6)),
            "bundles/pd/policy.onnx": (PD_BUNDLE / "policy.onnx").read_bytes(),
        },
        ["{tmp}/bundles/pd/manifest.json", "limits.torque_nm"],
    ),
    (
        "bundle-wrong-urdf-sha",
        LMPC,
        {
            "bundles/pd/manifest.json": _manifest(lambda m: m["robot"].__setitem__("urdf_sha256", "0" * 64)),
            "bundles/pd/policy.onnx": (PD_BUNDLE / "policy.onnx").read_bytes(),
        },
        ["{tmp}/bundles/pd/manifest.json", "urdf_sha256"],
    ),
]


def _run_case(
    hil: list[str], case: tuple[str, list[str], dict[str, str | bytes], list[str]], base: Path
) -> tuple[str, int, str, list[str]]:
    name, argv, files, expected = case
    tmp = base / name
    tmp.mkdir()
    for relative, content in files.items():
        path = tmp / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
    args = [a.replace("{tmp}", str(tmp)) for a in argv]
    env = {**os.environ, "COLUMNS": "200"}
    done = run([*hil, *args], check=False, capture_output=True, text=True, timeout=300, env=env, cwd=tmp)
    return name, done.returncode, done.stderr, [e.replace("{tmp}", str(tmp)) for e in expected]


def test_every_bad_input_is_one_line_naming_file_and_field_exit_2(tmp_path: Path, hil_command: list[str]) -> None:
    with ThreadPoolExecutor(max_workers=3) as pool:
        results = list(pool.map(lambda case: _run_case(hil_command, case, tmp_path), CASES))
    failures = []
    for name, code, stderr, expected in results:
        lines = [line for line in stderr.splitlines() if line.strip()]
        problems = []
        if code != 2:
            problems.append(f"exit {code}")
        if len(lines) != 1:
            problems.append(f"{len(lines)} stderr lines")
        if "Traceback" in stderr:
            problems.append("traceback")
        missing = [e for e in expected if e not in stderr]
        if missing:
            problems.append(f"missing {missing}")
        if problems:
            failures.append(f"{name}: {', '.join(problems)}: {stderr.strip()[-400:]!r}")
    assert not failures, "\n".join(failures)
    assert len(results) == len(CASES) >= 30
