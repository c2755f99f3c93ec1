"""``hil experiment`` checks every input before any work: a missing LMPC bundle is found before the
FB and HMPC runs, not after them (issue 20)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

import models.experiment as experiment
from hil_runtime.bundle import BundleError
from models.conditions import load_conditions
from models.experiment import ExperimentConfig, run_experiment
from models.robots import load_robot


def test_a_missing_lmpc_bundle_is_refused_before_any_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def no_work(*_args: Any, **_kwargs: Any) -> Any:
        raise AssertionError("a run started before every input was checked")

    monkeypatch.setattr(experiment, "simulate", no_work)
    robot = load_robot("ur5_paper")
    config = ExperimentConfig(laws=("pd",), modes=("fb", "hmpc", "lmpc"), plots=False, save_trajectories=False)
    empty = tmp_path / "bundles"
    empty.mkdir()
    with pytest.raises(BundleError, match=f"bundle directory {empty}: no bundle for law 'pd'"):
        run_experiment(
            robot, load_conditions(None, robot=robot)[:1], config, tmp_path / "out", {"lmpc": {"bundle_dir": empty}}
        )
