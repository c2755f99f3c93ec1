"""One policy call warm (back to back) and cold (right after the thread slept one period, as every
loop cycle does after its wait for the bus or the clock), per shipped bundle, beside the same for a
bare one-node onnxruntime graph. On a 2-core VM shared with other jobs, what ran on the CPU during
the sleep evicts the caches, and the cold call is what the loop pays (docs/runtime.md, "The
lock-step demo's rate").

    python benchmarks/bench_policy_cold.py [--laws pd,mrac] [--calls 2000] [--fifo 50 --cpu 1]

Prints one JSON document (µs median / p99 per law and state, cold/warm ratios, machine, load).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import benchinfo
import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _times_us(call: Callable[[], object], calls: int, sleep_s: float) -> dict[str, float]:
    times = []
    for _ in range(calls):
        if sleep_s:
            time.sleep(sleep_s)
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
    return benchinfo.spread(np.array(times[calls // 10 :]) * 1e6)


def _policy_call(law: str) -> Callable[[], object]:
    from hil_runtime.bundle import PolicyBundle

    bundle = PolicyBundle.load(ROOT / "models" / "bundles" / "ur5_paper" / law)
    n = bundle.n_joints
    q, zero, state = np.full(n, 0.1), np.zeros(n), np.zeros(bundle.state_size)
    return lambda: bundle.step(q, zero, q, zero, zero, state)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--laws", default="pd,mrac")
    parser.add_argument("--calls", type=int, default=2000)
    parser.add_argument("--period", type=float, default=0.001, help="the sleep before a cold call (s)")
    parser.add_argument("--fifo", type=int, default=None, help="SCHED_FIFO priority of this thread")
    parser.add_argument("--cpu", type=int, default=None, help="pin this thread to one CPU")
    args = parser.parse_args()
    applied = []
    if args.cpu is not None:
        os.sched_setaffinity(0, {args.cpu})
        applied.append(f"CPU {args.cpu}")
    if args.fifo is not None:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.fifo))
        applied.append(f"SCHED_FIFO {args.fifo}")
    from lmpc_graphs import bound_runner, make_session, one_node_graph

    load_before = list(os.getloadavg())
    calls: dict[str, Callable[[], object]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "one.onnx"
        one_node_graph(path, width=6, nodes=1)
        calls["onnx_1node"] = bound_runner(make_session(str(path)), width=6)
        for law in (x.strip() for x in args.laws.split(",") if x.strip()):
            calls[law] = _policy_call(law)
        results: dict[str, dict[str, Any]] = {}
        for name, call in calls.items():
            warm = _times_us(call, args.calls, 0.0)
            cold = _times_us(call, args.calls // 4, args.period)
            results[name] = {
                "warm_us": warm,
                "cold_us": cold,
                "cold_over_warm": round(cold["median"] / warm["median"], 2),
            }
    floor = results["onnx_1node"]
    for row in results.values():
        row["warm_over_onnx_1node_warm"] = round(row["warm_us"]["median"] / floor["warm_us"]["median"], 1)
    print(
        json.dumps(
            {
                "benchmark": "policy_cold",
                "command": " ".join(["python", "benchmarks/bench_policy_cold.py", *sys.argv[1:]]),
                "realtime": applied,
                "sleep_before_cold_call_s": args.period,
                "results": results,
                "machine": benchinfo.machine(),
                "load_average_before": load_before,
                "load_average_after": list(os.getloadavg()),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
