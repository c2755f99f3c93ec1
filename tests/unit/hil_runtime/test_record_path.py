"""``hil run --record``: the path checked before the run, the record written under exactly its name."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from hil_runtime.outputs import OutputError
from hil_runtime.record import RunRecord, check_record_path


def test_a_fifo_or_a_device_in_the_records_place_is_refused(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe.npz"
    os.mkfifo(fifo)
    with pytest.raises(OutputError, match="not a regular file") as info:
        check_record_path(fifo)
    assert str(fifo) in str(info.value) and info.value.exit_code == 2
    device = tmp_path / "full.npz"
    device.symlink_to("/dev/full")  # /dev/full under a record's name
    with pytest.raises(OutputError, match="not a regular file"):
        check_record_path(device)
    assert check_record_path(tmp_path / "run.npz") == "npz"


def test_a_name_without_the_suffix_is_still_written_under_exactly_that_name(tmp_path: Path) -> None:
    # np.savez appends '.npz' to a name without it ('run.NPZ' too): the rename then found nothing
    # and the written file stayed behind as a hidden partial one
    record = RunRecord(2, 1)
    record.n = 1
    record.save_npz(tmp_path / "run.NPZ")
    assert [p.name for p in tmp_path.iterdir()] == ["run.NPZ"]
