"""The builders of tests/integration/test_cli_bad_inputs.py's table (one bad input a row) and the
runner of one row through the installed ``hil``: kept apart so the table reads on its own."""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable
from pathlib import Path
from subprocess import run
from typing import Any

from sim_target.testing.ur5 import JOINT_NAMES

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


def _manifest(change: Callable[[dict[str, Any]], object]) -> str:
    manifest = json.loads((PD_BUNDLE / "manifest.json").read_text())
    change(manifest)
    return json.dumps(manifest)


def _experiment(mode: str) -> list[str]:
    return ["experiment", "--laws", "pd", "--modes", mode, "--timing-cycles", "5", "--no-plots", "--no-trajectories"]


EXPERIMENT = [*_experiment("fb"), "--out", "{tmp}/out"]
LMPC = [*_experiment("lmpc"), "--out", "{tmp}/out", "--lmpc-bundles", "{tmp}/bundles"]
Case = tuple[str, list[str], dict[str, str | bytes], list[str]]
FIFO = "\x00fifo"  # as a file's content: make a named pipe there instead


def _plot_case(name: str, content: str | bytes, *expected: str) -> Case:
    """``hil telemetry plot run.npz`` with ``content`` as the record (issue 20)."""
    return (name, ["telemetry", "plot", "{tmp}/run.npz"], {"run.npz": content}, ["{tmp}/run.npz", *expected])


def _runtime_yaml(telemetry: str) -> str:
    """A runtime config ``hil run --check`` accepts, with ``telemetry`` as its telemetry section."""
    joints = "".join(
        f"    - {{name: {name}, node_id: {i + 1}, max_torque_nm: 30.0}}\n" for i, name in enumerate(JOINT_NAMES)
    )
    return (
        f"robot: ur5_paper\nbundle: {{path: {PD_BUNDLE}, mode: lmpc}}\n"
        "bus:\n  transport: {interface: virtual, channel: check, fd: true, data_bitrate: 5000000}\n"
        f"  period_s: 0.001\n  joints:\n{joints}reference: {{kind: hold}}\ntelemetry: {telemetry}\n"
    )


def _telemetry_check_case(name: str, telemetry: str, files: dict[str, str | bytes], *expected: str) -> Case:
    """``hil run --config rt.yaml --check`` with ``telemetry`` as its section (issue 20)."""
    return (
        name,
        ["run", "--config", "{tmp}/rt.yaml", "--check"],
        {"rt.yaml": _runtime_yaml(telemetry), **files},
        ["rt.yaml", *expected],
    )


def _conditions_case(name: str, text: str | bytes, *expected: str) -> Case:
    """``hil experiment --conditions c.yaml`` with ``text`` as the file."""
    return (name, [*EXPERIMENT, "--conditions", "{tmp}/c.yaml"], {"c.yaml": text}, ["c.yaml", *expected])


def _urdf_case(name: str, text: str | bytes, *expected: str) -> Case:
    """``hil experiment --robot arm.urdf`` with ``text`` as the URDF."""
    return (name, [*EXPERIMENT, "--robot", "{tmp}/arm.urdf"], {"arm.urdf": text}, ["arm.urdf", *expected])


def _target_case(name: str, files: dict[str, str | bytes], *expected: str) -> Case:
    """``hil target serve --config t.yaml`` with ``files`` (t.yaml and what it names)."""
    return (name, ["target", "serve", "--config", "{tmp}/t.yaml"], files, ["t.yaml", *expected])


RUNTIME_YAML = (
    (ROOT / "deploy" / "runtime.ipc.yaml").read_text().replace("../models/bundles/ur5_paper/pd", str(PD_BUNDLE))
)


def _public_pem() -> bytes:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    return Ed25519PrivateKey.generate().public_key().public_bytes(Encoding.PEM, PublicFormat.SubjectPublicKeyInfo)


LAB_PUBLIC_PEM = _public_pem()


def _runtime_case(
    name: str,
    pattern: str,
    replacement: str,
    *expected: str,
    files: dict[str, str | bytes] | None = None,
    where: str = "r.yaml",
) -> Case:
    """``hil run --config r.yaml --check`` on deploy/runtime.ipc.yaml with one edit (a regex)."""
    text, count = re.subn(pattern, replacement, RUNTIME_YAML, count=1, flags=re.MULTILINE)
    assert count == 1, pattern
    return (
        name,
        ["run", "--config", "{tmp}/r.yaml", "--check"],
        {"r.yaml": text, **(files or {})},
        [where, *expected],
    )


def _record_case(name: str, record: str, files: dict[str, str | bytes], *expected: str) -> Case:
    """``hil run --record PATH`` on a valid config: refused before anything is started."""
    return (
        name,
        ["run", "--config", "{tmp}/r.yaml", "--record", record],
        {"r.yaml": RUNTIME_YAML, **files},
        list(expected),
    )


def _bundle_case(name: str, change: Callable[[dict[str, Any]], object], field: str) -> Case:
    """``hil experiment --modes lmpc`` on the PD bundle with its manifest edited by ``change``."""
    files: dict[str, str | bytes] = {
        "bundles/pd/manifest.json": _manifest(change),
        "bundles/pd/policy.onnx": (PD_BUNDLE / "policy.onnx").read_bytes(),
    }
    return (name, LMPC, files, ["{tmp}/bundles/pd/manifest.json", field])


def _run_case(
    hil: list[str], case: tuple[str, list[str], dict[str, str | bytes], list[str]], base: Path
) -> tuple[str, int, str, list[str]]:
    name, argv, files, expected = case
    tmp = base / name
    tmp.mkdir()
    for relative, content in files.items():
        path = tmp / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        if content == FIFO:
            os.mkfifo(path)
        elif isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
    args = [a.replace("{tmp}", str(tmp)) for a in argv]
    env = {**os.environ, "COLUMNS": "200"}
    done = run([*hil, *args], check=False, capture_output=True, text=True, timeout=300, env=env, cwd=tmp)
    return name, done.returncode, done.stderr, [e.replace("{tmp}", str(tmp)) for e in expected]
