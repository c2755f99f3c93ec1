"""``hil bundle keygen | sign | check``: a signed copy of a shipped bundle loads with its key only."""

from __future__ import annotations

import hashlib
import shutil
import stat
from pathlib import Path

import pytest

from hil_runtime.cli import main

SHIPPED = Path(__file__).resolve().parents[3] / "models" / "bundles" / "ur5_paper" / "pd"


def test_keygen_sign_and_check(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bundle = tmp_path / "pd"
    shutil.copytree(SHIPPED, bundle)
    graph_before = hashlib.sha256((bundle / "policy.onnx").read_bytes()).hexdigest()
    assert main(["bundle", "keygen", "--out", str(tmp_path / "lab")]) == 0
    assert main(["bundle", "keygen", "--out", str(tmp_path / "other")]) == 0
    assert stat.S_IMODE((tmp_path / "lab.key").stat().st_mode) == 0o600
    assert main(["bundle", "keygen", "--out", str(tmp_path / "lab")]) == 2  # never overwrites a key
    assert main(["bundle", "check", str(bundle), "--trusted-key", str(tmp_path / "lab.pub")]) == 2  # unsigned
    assert main(["bundle", "sign", str(bundle), "--key", str(tmp_path / "lab.key")]) == 0
    assert main(["bundle", "check", str(bundle), "--trusted-key", str(tmp_path / "lab.pub")]) == 0
    assert main(["bundle", "check", str(bundle), "--trusted-key", str(tmp_path / "other.pub")]) == 2
    assert main(["bundle", "sign", str(bundle), "--key", str(tmp_path / "lab.pub")]) == 2  # a public key
    assert hashlib.sha256((bundle / "policy.onnx").read_bytes()).hexdigest() == graph_before
    err = capsys.readouterr().err
    assert "signatures: none by a trusted key" in err and "not an unencrypted PEM private key" in err
