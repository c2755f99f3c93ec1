"""Free-running HIL at 1 kHz: ``hil run`` against ``hil target serve`` (clock realtime), both on
their own clocks, each on its own CPU with SCHED_FIFO (``hil demo --realtime``'s set-up), for one
law and mode. Prints JSON: the loop's period (median, p99, max), overruns, compute and exchange
times, the target's lateness (late ticks, skipped periods, worst lag, its physics thread's CPU
share), the run's validity, its scores, the machine and its load average; with
``--compare-lockstep`` also the lock-step run of the same law and mode and the relative change of
the composite score.

    python benchmarks/bench_hil_realtime.py --law pd --mode fb [--duration 5] [--condition C1]
    python benchmarks/bench_hil_realtime.py --law mrac --mode lmpc --duration 60   # a soak
    python benchmarks/bench_hil_realtime.py --all [--compare-lockstep]             # 6 laws x fb, lmpc

Run it on a quiet machine: the figures are the machine's (docs/runtime.md); the load average
before and after is in the JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

import benchinfo

LAWS = ("pd", "pid", "adrc", "hinf", "smc", "mrac")
MODES = ("fb", "lmpc")


def run_one(law: str, mode: str, duration_s: float | None, condition: str, realtime: bool, cpus: str) -> dict[str, Any]:
    """One ``hil demo`` run (headless), its figures."""
    from models.demo.options import DemoOptions
    from models.demo.run import run_demo

    options = DemoOptions(law=law, mode=mode, condition=condition, duration_s=duration_s, realtime=realtime, cpus=cpus)
    with tempfile.TemporaryDirectory(prefix="bench-hil-rt-") as tmp:
        results = run_demo(options, Path(tmp) / "out", headless=True)
    timing = results["timing"]
    scores = results["scores"]
    target = results.get("target") or {}
    return {
        "law": law,
        "mode": mode,
        "clock": "realtime" if realtime else "lockstep",
        "condition": condition,
        "duration_s": results["demo"]["duration_s"],
        "fault": results["fault"],
        "valid": results.get("valid", True),
        "invalid_reason": results.get("invalid_reason"),
        "cycles": timing["cycles"],
        "rate_hz": timing["rate_hz"],
        "overruns": timing["overruns"],
        "overrun_fraction": round(timing["overruns"] / timing["cycles"], 5) if timing["cycles"] else None,
        "skipped_periods": timing.get("skipped_periods"),
        "period_us": timing["period_us"],
        "compute_us": timing["compute_us"],
        "exchange_us": timing.get("exchange_us"),
        "target_lateness": target.get("lateness"),
        "target_realtime": target.get("realtime"),
        "composite_hil": scores["composite"]["hil"],
        "metrics_hil": scores["metrics"]["hil"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--law", choices=LAWS, default="pd")
    parser.add_argument("--mode", choices=MODES, default="fb")
    parser.add_argument("--all", action="store_true", help="every law in fb and lmpc")
    parser.add_argument("--duration", type=float, default=None, help="seconds (default: the condition's, 5 s)")
    parser.add_argument("--condition", default="C1")
    parser.add_argument("--cpus", default="auto", help="runtime,target CPUs: auto, none or R,T")
    parser.add_argument("--compare-lockstep", action="store_true", help="also run lock-step; compare the scores")
    args = parser.parse_args()
    load_before = [round(x, 2) for x in os.getloadavg()]
    pairs = [(law, mode) for mode in MODES for law in LAWS] if args.all else [(args.law, args.mode)]
    runs = []
    for law, mode in pairs:
        row: dict[str, Any]
        try:
            row = run_one(law, mode, args.duration, args.condition, True, args.cpus)
        except Exception as exc:  # noqa: BLE001 - one failing run is a row, the benchmark goes on
            row = {"law": law, "mode": mode, "clock": "realtime", "error": f"{type(exc).__name__}: {exc}"}
        if args.compare_lockstep and "error" not in row:
            lock = run_one(law, mode, args.duration, args.condition, False, args.cpus)
            row["lockstep_composite"] = lock["composite_hil"]
            row["lockstep_fault"] = lock["fault"]
            ref = lock["composite_hil"]
            row["composite_change_vs_lockstep"] = (
                round((row["composite_hil"] - ref) / ref, 4) if ref and math.isfinite(ref) else None
            )
        print(json.dumps(row), file=sys.stderr, flush=True)  # progress: one line per run
        runs.append(row)
    print(
        json.dumps(
            {
                "benchmark": "hil_realtime",
                "command": "python " + " ".join(sys.argv),
                "period_s": 1e-3,
                "runs": runs,
                "all_valid_without_fault": all(r.get("valid") and not r.get("fault") for r in runs),
                "machine": benchinfo.machine(),
                "load_average_before": load_before,
                "load_average_after": [round(x, 2) for x in os.getloadavg()],
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
