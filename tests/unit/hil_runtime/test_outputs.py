"""hil_runtime.outputs: --out checked before any work; files complete or absent; JSON-safe values."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hil_runtime.outputs import (
    OutputError,
    OutputWriteError,
    atomic_path,
    json_safe,
    prepare_output_dir,
    write_text_atomic,
)


def test_creates_missing_directories_and_leaves_no_probe(tmp_path: Path) -> None:
    out = prepare_output_dir(tmp_path / "a" / "b")
    assert out.is_dir() and list(out.iterdir()) == []


def test_a_file_in_the_way(tmp_path: Path) -> None:
    (tmp_path / "results").write_text("x")
    with pytest.raises(OutputError, match=r"--out .*results: a file is in the way") as info:
        prepare_output_dir(tmp_path / "results")
    assert info.value.exit_code == 2


def test_a_parent_that_is_a_file(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutputError, match=r"f is a file, not a directory"):
        prepare_output_dir(tmp_path / "f" / "sub" / "out")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a mode-555 directory; see the read-only-fs case")
def test_a_read_only_directory(tmp_path: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.raises(OutputError, match="not writable|cannot create"):
            prepare_output_dir(ro / "out")
    finally:
        ro.chmod(0o755)


def test_a_read_only_file_system() -> None:
    # /proc refuses new entries, even for root: the probe, not os.access, must find that out.
    with pytest.raises(OutputError, match=r"--out /proc/hil-out: cannot create the directory"):
        prepare_output_dir("/proc/hil-out")
    with pytest.raises(OutputError, match="not writable"):
        prepare_output_dir("/proc/self")


def test_atomic_write_replaces_completely(tmp_path: Path) -> None:
    target = tmp_path / "results.json"
    write_text_atomic(target, "old")
    write_text_atomic(target, "new")
    assert target.read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["results.json"]


@pytest.mark.parametrize("failure", [OSError(errno.ENOSPC, "No space left on device"), KeyboardInterrupt()])
def test_a_failure_midway_leaves_the_old_file_and_no_partial(tmp_path: Path, failure: BaseException) -> None:
    target = tmp_path / "table.md"
    target.write_text("previous complete table")
    expected = OutputWriteError if isinstance(failure, OSError) else KeyboardInterrupt
    with pytest.raises(expected) as info, atomic_path(target) as tmp:
        tmp.write_text("half of a tab")
        raise failure
    assert target.read_text() == "previous complete table"
    assert [p.name for p in tmp_path.iterdir()] == ["table.md"]
    if expected is OutputWriteError:
        assert str(info.value) == f"{target}: cannot write (No space left on device)"
        assert isinstance(info.value, OutputWriteError) and info.value.exit_code == 1


def test_numpy_keeps_the_temporary_suffix(tmp_path: Path) -> None:
    np = pytest.importorskip("numpy")
    target = tmp_path / "run.npz"
    with atomic_path(target) as tmp:
        np.savez_compressed(tmp, a=np.arange(3))
    assert np.load(target)["a"].tolist() == [0, 1, 2]
    assert [p.name for p in tmp_path.iterdir()] == ["run.npz"]


def test_importing_it_is_light() -> None:
    code = "import sys, hil_runtime.outputs; sys.exit(1 if 'numpy' in sys.modules or 'models' in sys.modules else 0)"
    assert subprocess.run([sys.executable, "-c", code], check=False, timeout=60).returncode == 0


def test_json_safe_makes_plain_strict_json() -> None:
    import numpy as np

    value = {
        "nan": float("nan"),
        "inf": float("-inf"),
        "f64": np.float64(1.5),
        "f32_nan": np.float32("nan"),
        "i64": np.int64(7),
        "flag": np.bool_(True),
        "array": np.array([[1.0, np.inf], [2.0, 3.0]]),
        "scalar_array": np.array(4),
        "nested": ({"k": (np.float64(np.nan), 2)},),
        3: "int key",
        "text": "nan",
        "none": None,
    }
    safe = json_safe(value)
    assert safe == {
        "nan": None,
        "inf": None,
        "f64": 1.5,
        "f32_nan": None,
        "i64": 7,
        "flag": True,
        "array": [[1.0, None], [2.0, 3.0]],
        "scalar_array": 4,
        "nested": [{"k": [None, 2]}],
        "3": "int key",
        "text": "nan",
        "none": None,
    }
    # plain Python types all the way down, so strict JSON accepts it and reads it back equal
    assert type(safe["f64"]) is float and type(safe["i64"]) is int and type(safe["flag"]) is bool
    assert type(safe["array"][0][0]) is float and type(safe["scalar_array"]) is int
    assert json.loads(json.dumps(safe, allow_nan=False)) == safe
