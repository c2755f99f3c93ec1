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


def test_check_applies_the_sensing_gate_at_the_stated_noise(capsys: pytest.CaptureFixture[str]) -> None:
    """``hil bundle check --encoder-noise-rad``: the runtime's sensing gate, its predicted steps printed."""
    assert main(["bundle", "check", str(SHIPPED)]) == 0
    out = capsys.readouterr().out
    assert "noise 1e-05 rad: torque steps " in out and "bound 1.17, 1.17, 0.76" in out, out
    noisy = ["--encoder-noise-rad", "3e-4", "--velocity-noise-rad-s", "0.2"]
    assert main(["bundle", "check", str(SHIPPED), *noisy]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "into torque steps of" in err and "on joint 2" in err, err
    assert main(["bundle", "check", str(SHIPPED), "--encoder-noise-rad", "-1"]) == 2
    assert "--encoder-noise-rad: must be a finite RMS noise >= 0" in capsys.readouterr().err
