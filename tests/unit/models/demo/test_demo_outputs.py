"""hil demo's output files (models/demo/report.py): the summary of a faulted run says so and marks
what it cannot compare; results.json carries numpy values as numbers and non-finite ones as null."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from models.demo import report
from models.scoring import METRICS


def _results(fault: str | None) -> dict[str, Any]:
    metrics = {m: 0.1 for m in METRICS}
    return {
        "demo": {
            "law": "mrac",
            "mode": "lmpc",
            "condition": "C1",
            "realtime": False,
            "bundle": "models/bundles/ur5_paper/mrac",
            "period_s": 1e-3,
            "duration_s": 5.0,
            "disturbance_s": 2.0,
        },
        "fault": fault,
        "scores": {
            "metrics": {"hil": {**metrics, "settle_s": 0.5}, "sim": {**metrics, "settle_s": 0.0}},
            "relative": {**{m: 0.0 for m in METRICS}, "settle_s": math.inf},
            "composite": {"hil": 1.0, "sim": 0.5},
            "within_limits": {"hil": fault is None, "sim": True},
            "trajectory_rms_diff_deg": 0.01,
            "trajectory_max_diff_deg": 0.02,
            "fallback_cycles": {"hil": 3},
        },
        "timing": {
            "cycles": 812,
            "rate_hz": 998.0,
            "overruns": 0,
            "telemetry_sent": 812,
            "telemetry_dropped": 0,
            "period_us": {"median": 1000.0, "p99": 1100.0, "max": 1500.0},
            "compute_us": {"median": 40.0, "p99": 90.0, "max": None},
            "exchange_us": None,
        },
        "telemetry": {"samples": 812, "missing": 0},
        "shutdown": {
            "drives_stopped": True,
            "drives_operation_enabled_after_stop": [False] * 6,
            "runtime_exit_code": 0,
            "target_exit_code": 0,
            "processes_alive": [],
            "ipc_sockets_left": [],
            "work_dir_removed": True,
        },
        "processes": {"runtime": {"stop_s": 0.1}},
        "load_average": [1.0, 1.0, 1.0],
    }


def test_the_summary_of_a_faulted_run_says_so_and_marks_what_it_cannot_compare() -> None:
    clean = report.format_summary(_results(None))
    faulted = report.format_summary(_results("velocity_limit: joint 6"))
    assert "FAULTED" not in clean and "# hil demo: MRAC LMPC on C1" in clean
    assert "**The runtime FAULTED** after 812 cycles: velocity_limit: joint 6" in faulted
    assert "Inside the joint limits: HIL NO, simulation yes" in faulted
    assert "| settling after the disturbance (s) | 0.5 | 0 | — |" in clean  # infinite relative change
    assert "| composite (normalized between the two) | 1.000 | 0.500 | +100.0 |" in clean
    assert "| exchange on the bus (µs) | — | — | — |" in clean  # no exchange figures recorded


def test_results_json_has_numbers_and_nulls_only(tmp_path: Path) -> None:
    values: dict[Any, Any] = {  # numpy values and a non-string key on purpose
        "numpy": {"float": np.float64(0.25), "int": np.int64(3), "bool": np.bool_(True)},
        "non_finite": [math.nan, math.inf, np.float64(-np.inf)],
        "tuple": (1, 2.5),
        7: "a key that is not a string",
    }
    report.write_json(tmp_path / "results.json", values)
    text = (tmp_path / "results.json").read_text()
    assert json.loads(text) == {
        "numpy": {"float": 0.25, "int": 3, "bool": True},
        "non_finite": [None, None, None],
        "tuple": [1, 2.5],
        "7": "a key that is not a string",
    }
    assert "NaN" not in text and "Infinity" not in text


def test_a_free_running_run_whose_plant_fell_behind_is_marked_invalid() -> None:
    from sim_target.lateness import invalid_reason

    late = {
        "periods": 5000,
        "late_ticks": 7,
        "skipped_periods": 9,
        "skipped_fraction": 9 / 5000,
        "worst_lag_s": 4e-4,
        "cpu_fraction": 0.2,
    }
    results = _results(None)
    results["demo"]["realtime"] = True
    results["invalid_reason"] = invalid_reason(late, 1e-3)
    results["target"] = {"lateness": late, "realtime": {"substeps": 8, "applied": ["SCHED_FIFO 80"]}}
    summary = report.format_summary(results)
    assert "**INVALID RUN**: the plant skipped 9 of 5000 periods (0.18 % > 0.1 %)" in summary
    assert "not valid HIL scores" in summary
    assert "Target: 5000 periods, late ticks 7, skipped 9 (0.180 %), worst lag 400 µs" in summary
    clean = report.format_summary(_results(None))
    assert "INVALID" not in clean and "Target:" not in clean  # lock-step: no wall clock to lag
