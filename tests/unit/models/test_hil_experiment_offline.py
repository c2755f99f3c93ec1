"""models/hil_experiment/ without the target: conditions handed to the runtime exactly, the
target's run start, padding of a faulted record, parity arithmetic, the Table II layout."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from hil_runtime.conditions import parse_conditions
from hil_runtime.supervisor import FaultKind
from models.conditions import load_conditions, random_conditions
from models.hil_experiment import PAPER_TABLE_II, HilRun, conditions_yaml, initial_state, run_start
from models.hil_experiment.parity import parity, per_run_scores
from models.hil_experiment.tables import format_parity_table
from models.hil_experiment.target_runs import pad_record
from models.lab.runs import is_rig_fault
from models.robots import load_robot
from sim_target.config import ImpulseFault, RunStart, TargetConfigError, TargetLayout, check_run_start, parse_run_start

LAYOUT = TargetLayout(tuple(f"j{i}" for i in range(6)), (-3.14,) * 6, (3.14,) * 6, (1, 2, 3, 4, 5, 6))


def test_conditions_reach_the_runtime_exactly() -> None:
    robot = load_robot("ur5_paper")
    conditions = load_conditions() + random_conditions(robot, 3, seed=7)
    again = parse_conditions(yaml.safe_load(conditions_yaml(conditions)), "round trip")
    assert again == conditions  # every float, the disturbance, the mismatch, the initial state


def test_run_start_is_the_simulators_initial_state_and_disturbance() -> None:
    c4 = {c.name: c for c in load_conditions()}["C4"]
    start = parse_run_start(run_start(c4))
    q0, qd0 = initial_state(c4)
    np.testing.assert_allclose(start.position_rad, c4.reference(0.0)[0])
    assert start.velocity_rad_s is not None
    np.testing.assert_allclose(start.velocity_rad_s, c4.reference(0.0)[1])  # C4 starts moving
    assert np.abs(qd0).max() > 0.1 and np.allclose(q0, start.position_rad)
    (impulse,) = start.faults
    assert isinstance(impulse, ImpulseFault)
    assert (impulse.at_s, impulse.duration_s, impulse.torque_nm) == (2.0, 2e-5, (1.0, 1.0, 5.0, 5.0, 10.0, 10.0))
    check_run_start(start, LAYOUT)


@pytest.mark.parametrize(
    ("start", "message"),
    [
        ({"position_rad": [0.0] * 5}, "position_rad: 5 values for 6 joints"),
        ({"position_rad": [0.0] * 6, "velocity_rad_s": [0.0] * 7}, "velocity_rad_s: 7 values for 6 joints"),
        ({"position_rad": [0.0] * 5 + [4.0]}, "position_rad[5]: 4 rad is outside joint 'j5'"),
        ({"position_rad": [0.0] * 6, "faults": [{"kind": "impulse", "torque_nm": [1.0]}]}, "torque_nm: 1 values"),
    ],
)
def test_run_start_refusals(start: dict, message: str) -> None:
    with pytest.raises(TargetConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        check_run_start(parse_run_start({"kind": "start", **start}), LAYOUT)


def test_run_start_schema_refuses_nan() -> None:
    with pytest.raises(TargetConfigError, match="position_rad"):
        parse_run_start({"kind": "start", "position_rad": [math.nan] * 6})
    assert isinstance(parse_run_start({"kind": "start", "position_rad": [0.0] * 6}), RunStart)


def test_a_faulted_record_is_held_at_its_last_position() -> None:
    rows, steps = 3, 6
    record = {
        "t_s": np.arange(rows) * 1e-3,
        "q": np.arange(rows * 2, dtype=float).reshape(rows, 2),
        "qd": np.ones((rows, 2)),
        "tau": np.ones((rows, 2)),
        "compute_s": np.ones(rows),
    }
    out = pad_record(record, steps, 1e-3)
    np.testing.assert_allclose(out["t"], np.arange(steps) * 1e-3)
    np.testing.assert_allclose(out["q"][rows:], np.repeat(record["q"][-1:], steps - rows, axis=0))
    np.testing.assert_allclose(out["qd"][rows:], 0.0)  # braked
    np.testing.assert_allclose(out["tau"][rows:], 0.0)
    assert HilRun(out, rows, "feedback_timeout: x", {}, rig_fault=is_rig_fault(FaultKind.FEEDBACK_TIMEOUT)).rig_fault
    assert not HilRun(out, rows, "position_limit: x", {}, rig_fault=is_rig_fault(FaultKind.POSITION_LIMIT)).rig_fault


def test_a_rig_fault_is_told_by_its_kind_never_by_its_text() -> None:
    """models.lab.runs classifies Runtime.last_fault's FaultKind: the bus and the drives' state are
    the rig's, a limit or a bad policy output the controller's, whatever the detail text says."""
    assert {k for k in FaultKind if is_rig_fault(k)} == {
        FaultKind.FEEDBACK_TIMEOUT,
        FaultKind.HEARTBEAT_LOST,
        FaultKind.TRANSPORT,
        FaultKind.DRIVE_STATE,
        FaultKind.STALE_FEEDBACK,
    }
    assert not is_rig_fault(None)
    assert not is_rig_fault(FaultKind.VELOCITY_LIMIT)


def test_per_run_scores_normalize_within_a_condition() -> None:
    metrics = {"rmse": 1.0, "mae": 1.0, "p95": 1.0, "peak": 1.0, "settle_s": 1.0, "dedt_rms": 1.0}
    half = {k: v / 2 for k, v in metrics.items()}
    runs = [
        {"law": "pd", "mode": m, "condition": "C1", "metrics": x, "finite": True, "within_limits": True}
        for m, x in (("fb", metrics), ("lmpc", half))
    ]
    scores = per_run_scores(runs)
    assert scores[("pd", "fb", "C1")] == pytest.approx(1.0)
    assert scores[("pd", "lmpc", "C1")] == pytest.approx(0.5)
    # On another table's scale (parity: the simulation's), a run is scored against that table's maxima.
    worse = [{**runs[1], "mode": "fb", "metrics": {k: 4 * v for k, v in metrics.items()}}]
    assert per_run_scores(worse, scale=runs)[("pd", "fb", "C1")] == pytest.approx(4.0)


def test_parity_never_averages_a_run_that_faulted_in_either_plant(tmp_path: Path) -> None:
    metrics = {"rmse": 1.0, "mae": 1.0, "p95": 1.0, "peak": 1.0, "settle_s": 1.0, "dedt_rms": 1.0}
    t = np.linspace(0.0, 1.0, 11)
    traj: dict[str, np.ndarray] = {"t": t, "q": np.zeros((11, 6)), "tau": np.zeros((11, 6))}

    def run(cond: str, within: bool, scale: float) -> dict:
        return {"law": "pd", "mode": "fb", "condition": cond, "finite": True, "within_limits": within,
                "metrics": {k: scale * v for k, v in metrics.items()}}  # fmt: skip

    sim = {"runs": [run("C1", True, 1.0), run("C2", True, 1.0)], "table": {"pd": {"fb": {"score": 1.0}}}, "config": {},
           "all_runs_finite_and_within_limits": True}  # fmt: skip
    for cond in ("C1", "C2"):
        np.savez(tmp_path / f"pd_fb_{cond}.npz", t=traj["t"], q=traj["q"], tau=traj["tau"])
    trajectories = {("pd", "fb", c): traj for c in ("C1", "C2")}
    # C2 faulted on the HIL after a good start: its (partial) score is lower, it must not count.
    hil_runs = [run("C1", True, 1.02), run("C2", False, 0.1)]
    hil = {"runs": hil_runs, "table": {"pd": {"fb": {"score": 0.5}}}}
    row = parity(hil, sim, trajectories, tmp_path)["table"]["pd"]["fb"]
    assert (row["runs_compared"], row["runs_failed"]) == (1, 1)
    assert row["score_rel"] == pytest.approx(0.02) and row["within_tolerance"]
    assert "+2.0 ✗1" in "\n".join(format_parity_table(parity(hil, sim, trajectories, tmp_path), ["fb"]))
    # every run failed: no figure, never a within-tolerance verdict
    hil_runs[0]["within_limits"] = False
    row = parity(hil, sim, trajectories, tmp_path)["table"]["pd"]["fb"]
    assert row["score_rel"] is None and row["score_hil"] is None and not row["within_tolerance"]
    assert "| — | — | — ✗2 |" in "\n".join(format_parity_table(parity(hil, sim, trajectories, tmp_path), ["fb"]))


def test_paper_table_ii_values() -> None:  # the paper's Table II (hardware), FB -> LMPC
    assert PAPER_TABLE_II["pd"] == (0.997, 0.661) and PAPER_TABLE_II["smc"] == (0.245, 0.007)
    assert set(PAPER_TABLE_II) == {"pd", "pid", "adrc", "hinf", "smc", "mrac"}


def test_a_free_running_record_is_put_on_period_slots_holding_over_skipped_ones() -> None:
    from models.hil_experiment.target_runs import resample_record

    t_s = np.array([0.0, 1.0, 2.0, 5.0, 6.0]) * 1e-3  # slots 3 and 4 skipped by the loop
    record = {"t_s": t_s, "q": np.arange(5, dtype=float)[:, None], "compute_s": np.ones(5)}
    out = resample_record(record, 1e-3)
    np.testing.assert_allclose(out["t_s"], np.arange(7) * 1e-3)
    np.testing.assert_allclose(out["q"][:, 0], [0, 1, 2, 2, 2, 3, 4])
    padded = pad_record(out, 7, 1e-3)  # one row per period: what the lock-step path checks
    np.testing.assert_allclose(padded["q"][:, 0], [0, 1, 2, 2, 2, 3, 4])
    assert resample_record(record, 1e-3, max_rows=4)["q"].shape == (4, 1)  # the condition's length


def test_free_running_needs_the_target_in_its_own_process() -> None:
    from models.errors import ModelInputError
    from models.experiment import ExperimentConfig
    from models.hil_experiment.config import HilOptions, check_hil_inputs

    robot = load_robot("ur5_paper")
    config = ExperimentConfig(laws=("pd",), modes=("fb",))
    with pytest.raises(ModelInputError, match="--clock realtime: the target must run in its own process"):
        check_hil_inputs(robot, [], config, HilOptions(clock="realtime"))
    with pytest.raises(ModelInputError, match="--clock: unknown 'fast'"):
        check_hil_inputs(robot, [], config, HilOptions(clock="fast", transport="ipc"))
