"""``hil run --record``: the path checked before the run, the record written under exactly its name."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from hil_runtime.outputs import OutputError
from hil_runtime.record import RECORD_SUFFIXES, RunRecord, check_record_path


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda tmp: Path("/dev/full"), "not a regular file"),
        (lambda tmp: (tmp / "d.npz").mkdir() or tmp / "d.npz", "a directory"),
        (lambda tmp: tmp / "run", "the name must end in .npz"),
        (lambda tmp: tmp / "run.NPZ", "the name must end in .npz"),
        (lambda tmp: tmp / "missing" / "run.npz", "is not an existing directory"),
        (lambda tmp: (tmp / "f").write_text("x") and tmp / "f" / "run.npz", "is not an existing directory"),
    ],
)
def test_an_unusable_record_path_is_refused_before_the_run(
    tmp_path: Path, make: Callable[[Path], Path], message: str
) -> None:
    path = make(tmp_path)
    with pytest.raises(OutputError) as info:
        check_record_path(path)
    assert message in str(info.value) and str(path) in str(info.value) and info.value.exit_code == 2


def test_a_fifo_is_refused(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe.npz"
    os.mkfifo(fifo)
    with pytest.raises(OutputError, match="not a regular file"):
        check_record_path(fifo)


def test_the_allowed_suffixes_are_a_parameter(tmp_path: Path) -> None:
    assert RECORD_SUFFIXES == (".npz",)
    assert check_record_path(tmp_path / "run.mcap", (".npz", ".mcap")) == tmp_path / "run.mcap"
    assert check_record_path(tmp_path / "run.npz") == tmp_path / "run.npz"
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # the write probe is gone


def test_the_record_is_written_under_its_name_and_nothing_else_is_left(tmp_path: Path) -> None:
    record = RunRecord(4, 2)
    record.n = 3
    record.q[:3] = 1.0
    target = tmp_path / "run.npz"
    record.save_npz(target)
    assert [p.name for p in tmp_path.iterdir()] == ["run.npz"]
    with np.load(target) as data:
        assert data["q"].shape == (3, 2) and float(data["q"].sum()) == 6.0


def test_a_name_without_the_suffix_is_still_written_under_exactly_that_name(tmp_path: Path) -> None:
    # np.savez appends '.npz' to a bare name: the rename then found nothing and a hidden partial stayed
    record = RunRecord(2, 1)
    record.n = 1
    record.save_npz(tmp_path / "run")
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
