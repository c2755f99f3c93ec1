"""models.lmpc.h5file: the one HDF5 writer and reader of the pipeline (raw dataset, labels)."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from models.errors import ModelInputError
from models.lmpc.h5file import read_h5, write_h5, write_manifest
from models.lmpc.pipeline import load_labels


def test_written_file_reads_back_with_its_manifest(tmp_path) -> None:
    path = tmp_path / "sub" / "x.h5"
    with write_h5(path) as h5:
        h5.create_dataset("a", data=np.arange(3.0))
        write_manifest(h5, {"schema": "s/1", "n": 3})
    assert sorted(p.name for p in path.parent.iterdir()) == ["x.h5"]  # no temporary file left
    with read_h5(path, "thing", "s/1") as (h5, manifest):
        assert manifest == {"schema": "s/1", "n": 3}
        np.testing.assert_array_equal(h5["a"][...], [0.0, 1.0, 2.0])


def test_a_failed_write_leaves_neither_the_file_nor_a_temporary(tmp_path) -> None:
    path = tmp_path / "x.h5"
    with pytest.raises(RuntimeError, match="boom"), write_h5(path) as h5:
        h5.create_dataset("a", data=np.zeros(2))
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_reader_refusals_are_one_line_naming_the_file(tmp_path) -> None:
    path = tmp_path / "x.h5"
    with pytest.raises(ModelInputError, match=f"labels {path}: no such file \\(run the label stage first\\)"):
        load_labels(path)
    with write_h5(path) as h5:
        write_manifest(h5, {"schema": "other/1"})
    with pytest.raises(ModelInputError, match="unknown schema 'other/1' \\(expected hil-lmpc-labels/1\\)"):
        load_labels(path)
    with h5py.File(path, "w") as h5:  # no manifest attribute at all
        h5.create_dataset("a", data=np.zeros(2))
    with pytest.raises(ModelInputError, match="unreadable or truncated HDF5") as info:
        load_labels(path)
    assert "\n" not in str(info.value) and info.value.exit_code == 2
    with write_h5(path) as h5:
        write_manifest(h5, {"schema": "s/1"})
    with pytest.raises(ModelInputError, match=f"thing {path}: unreadable or truncated HDF5"):  # raised in the block
        with read_h5(path, "thing", "s/1") as (h5, _):
            h5["missing"][...]
