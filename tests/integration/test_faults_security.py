"""The campaign's security rows outside ``--quick`` (issue 20): a second heartbeat sender on the
ipc bus, a second master's NMT command, the bus directory squatted by another user, a flood of
frames on our drives' identifiers; each must pass (docs/faults.md, docs/security.md)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SLOW_ROWS = ("second_sender", "second_master_nmt", "squatted_bus_directory", "wrong_length_flood")


@pytest.mark.heavy
def test_the_security_rows_pass(tmp_path: Path) -> None:
    out = tmp_path / "faults"
    command = [sys.executable, "-m", "hil_runtime.cli", "faults", "--only", ",".join(SLOW_ROWS), "--repeats", "1"]
    done = subprocess.run([*command, "--out", str(out)], capture_output=True, text=True, timeout=600, check=False)
    document = json.loads((out / "results.json").read_text())
    failed = {row["fault"]: row["failures"] for row in document["rows"] if not row["pass"]}
    assert done.returncode == 0 and not failed, f"{failed}\n{done.stderr[-3000:]}"
    assert sorted(row["fault"] for row in document["rows"]) == sorted(SLOW_ROWS)
