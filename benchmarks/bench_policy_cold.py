"""One policy call warm (back to back) and cold (right after the thread slept one period, as every
loop cycle does after its wait for the bus or the clock), per shipped bundle, beside the same for a
bare one-node onnxruntime graph. On a 2-core VM shared with other jobs, what ran on the CPU during
the sleep evicts the caches, and the cold call is what the loop pays (docs/runtime.md, "The
lock-step demo's rate"). Beside them, "hybrid": the same period waited as the pacer's hybrid wait
does (sleep to ``--spin-us`` before the call, then spin; ``loop.spin_s``), cold and hybrid blocks
interleaved so the machine's load moves both alike.

    python benchmarks/bench_policy_cold.py [--laws pd,mrac] [--calls 2000] [--fifo 50 --cpu 1] [--spin-us 200]

Prints one JSON document (µs median / p99 per law and state, cold/warm ratios, machine, load).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import benchinfo
import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _times_s(call: Callable[[], object], calls: int, sleep_s: float, spin_s: float = 0.0) -> list[float]:
    """Each call's time after sleeping ``sleep_s - spin_s`` and spinning ``spin_s``."""
    times = []
    clock = time.perf_counter
    for _ in range(calls):
        if sleep_s:
            time.sleep(sleep_s - spin_s)
            spun = clock() + spin_s
            while clock() < spun:
                pass
        t0 = clock()
        call()
        times.append(clock() - t0)
    return times[calls // 10 :]


def _times_us(call: Callable[[], object], calls: int, sleep_s: float) -> dict[str, float]:
    return benchinfo.spread(np.array(_times_s(call, calls, sleep_s)) * 1e6)


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
    parser.add_argument("--spin-us", type=float, default=200.0, help="the hybrid wait's spin before a call")
    args = parser.parse_args()
    applied = []
    if args.cpu is not None:
        os.sched_setaffinity(0, {args.cpu})
        applied.append(f"CPU {args.cpu}")
    if args.fifo is not None:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.fifo))
        applied.append(f"SCHED_FIFO {args.fifo}")
    from lmpc_graphs import bound_runner, make_session, one_node_graph

    load_before = benchinfo.load_average()
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
            cold_s: list[float] = []
            hybrid_s: list[float] = []
            for _ in range(4):  # interleaved blocks
                cold_s += _times_s(call, args.calls // 16, args.period)
                hybrid_s += _times_s(call, args.calls // 16, args.period, args.spin_us * 1e-6)
            cold = benchinfo.spread(np.array(cold_s) * 1e6)
            hybrid = benchinfo.spread(np.array(hybrid_s) * 1e6)
            results[name] = {
                "warm_us": warm,
                "cold_us": cold,
                "hybrid_us": hybrid,
                "cold_over_warm": round(cold["median"] / warm["median"], 2),
                "hybrid_over_warm": round(hybrid["median"] / warm["median"], 2),
            }
    floor = results["onnx_1node"]
    for row in results.values():
        row["warm_over_onnx_1node_warm"] = round(row["warm_us"]["median"] / floor["warm_us"]["median"], 1)
    print(
        benchinfo.report(
            "policy_cold",
            load_before,
            {
                "realtime": applied,
                "sleep_before_cold_call_s": args.period,
                "hybrid_spin_s": args.spin_us * 1e-6,
                "results": results,
            },
        )
    )


if __name__ == "__main__":
    main()
