"""Microseconds per dynamics call, own RNE vs pinocchio, single and batched. Prints JSON.

python benchmarks/bench_dynamics.py [--robot ur5_paper] [--batch 64]
"""

from __future__ import annotations

import argparse
import json
import time

import benchinfo
import numpy as np

from models.dynamics import make_dynamics
from models.robots import load_robot


def _time_us(fn, repeats: int) -> dict[str, float]:
    fn()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - start) * 1e6)
    return {"median_us": float(np.median(samples)), "p99_us": float(np.percentile(samples, 99))}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--robot", default="ur5_paper")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=300)
    args = parser.parse_args()
    robot = load_robot(args.robot)
    rng = np.random.default_rng(0)
    results = {}
    for backend in ("rne", "pinocchio"):
        dyn = make_dynamics(robot, backend)
        for batch in (1, args.batch):
            q, qd, qdd = (rng.uniform(-2, 2, (batch, robot.n_joints)) for _ in range(3))
            if batch == 1:
                q, qd, qdd = q[0], qd[0], qdd[0]
            for name, fn in {
                "inverse_dynamics": lambda: dyn.inverse_dynamics(q, qd, qdd),
                "mass_matrix": lambda: dyn.mass_matrix(q),
                "nonlinear_effects": lambda: dyn.nonlinear_effects(q, qd),
                "forward_dynamics": lambda: dyn.forward_dynamics(q, qd, qdd),
            }.items():
                stats = _time_us(fn, args.repeats)
                stats["per_state_median_us"] = stats["median_us"] / batch
                results[f"{backend}/{name}/batch{batch}"] = stats
    print(
        json.dumps(
            {
                "benchmark": "dynamics",
                "robot": robot.name,
                "n_joints": robot.n_joints,
                "results": results,
                "machine": benchinfo.machine("numpy", "pin", "torch"),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
