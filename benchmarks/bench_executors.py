"""Executors (JSON on stdout): wall time of one HMPC labeling batch on local processes vs a local Ray.

    python benchmarks/bench_executors.py --states 4000 --workers 2 --rounds 3

The batch: states visited by the PD law alone on the paper's five conditions (as in
``bench_hmpc.labeling_states``), cold HMPC solves with the labeling options, ``solve_batch`` in chunks
of 256. Each executor is started once (process pool / ``ray.init``: its start-up time is reported
apart), warmed on a few states, then the batch is labeled ``--rounds`` times, the two executors
interleaved round by round so that both see the same machine load. The 1-min load average is
recorded before and after every timed batch; the labels are compared bit for bit.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Any

import numpy as np
from bench_hmpc import head, labeling_states
from benchinfo import machine


def load() -> float:
    return round(os.getloadavg()[0], 2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--states", type=int, default=4000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--executors", default="local,ray")
    options = parser.parse_args()

    from models.executors import make_executor
    from models.hmpc import HMPCConfig, solve_batch
    from models.lmpc.labels import LABEL_HMPC_OPTIONS

    law, robot, args = labeling_states(options.states)
    config = HMPCConfig.from_options(**LABEL_HMPC_OPTIONS)
    names = [n.strip() for n in options.executors.split(",") if n.strip()]
    executors = {name: make_executor(name, options.workers) for name in names}
    out: dict[str, Any] = {
        "benchmark": "executors: HMPC labeling batch wall time",
        "states": options.states,
        "workers": options.workers,
        "chunk_states": 256,
        "machine": machine("ray", "numpy", "numba"),
        "start_s": {},
        "rounds": {name: [] for name in names},
    }
    labels: dict[str, np.ndarray] = {}
    try:
        for name, executor in executors.items():
            started = time.perf_counter()
            warm = head(args, 2 * options.workers)  # start the workers, build their solvers
            solve_batch(law, robot, *warm, config=config, executor=executor, chunk_states=1)
            out["start_s"][name] = round(time.perf_counter() - started, 2)
        for _ in range(options.rounds):
            for name, executor in executors.items():
                before = load()
                started = time.perf_counter()
                tau, _ = solve_batch(law, robot, *args, config=config, executor=executor)
                wall_s = time.perf_counter() - started
                out["rounds"][name].append(
                    {
                        "wall_s": round(wall_s, 3),
                        "states_per_s": round(options.states / wall_s),
                        "load": [before, load()],
                    }
                )
                labels[name] = tau
    finally:
        for executor in executors.values():
            executor.close()
    out["median_wall_s"] = {name: float(np.median([r["wall_s"] for r in rows])) for name, rows in out["rounds"].items()}
    out["labels_bit_equal"] = all(np.array_equal(labels[names[0]], t) for t in labels.values())
    out["load_average_end"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
