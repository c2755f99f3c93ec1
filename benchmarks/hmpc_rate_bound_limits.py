"""Does the deployable HMPC (the structured pipeline's expert) stay inside a robot's limits? Per law,
on the pipeline's first training condition (paper-range draw, seed 7101, the robot's default
disturbance), the largest position and velocity ratio to the limits: the formulation as the robot runs
it (its torque-rate bound, models.hmpc.config.formulation_options), without the rate bound, and with
the bound but predicting in control-period steps (docs/any_arm.md, "Torque-rate bound"). Prints JSON.

    python benchmarks/hmpc_rate_bound_limits.py --robot ur5 [--conditions 1] [--duration-s 2.4]
    python benchmarks/hmpc_rate_bound_limits.py --robot ur5 --sweep    # PD only: rate x prediction step

``--sweep``: why the formulation predicts in 10 ms steps: PD's HMPC under bounds of 1000, 3000 and
10000 N·m/s with 1 ms steps, and at the robot's bound with 5 ms steps, 20 steps of 1 ms and a 10x
smoothness weight.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from typing import Any

import benchinfo
import numpy as np

from models.feedback import LAW_NAMES, make_law
from models.hmpc import make_hmpc_controller
from models.hmpc.config import formulation_options
from models.lmpc.paper_range import paper_range_conditions
from models.lmpc.structured import StructuredConfig
from models.robots import load_robot
from models.sim import ControllerStack, SimConfig, simulate


def variant(
    robot: Any, conditions: list[Any], options: dict[str, Any], law_names: tuple[str, ...] = LAW_NAMES
) -> dict[str, Any]:
    """Every law's HMPC side by side on ``conditions``: per law the worst ratios and the first violation."""
    laws = [make_law(name, robot, 1e-3, "designed") for name in law_names]
    controllers = [make_hmpc_controller(law, robot, **options) for law in laws]
    started = time.perf_counter()
    batch = [c for _ in controllers for c in conditions]
    stack = ControllerStack(controllers, [len(conditions)] * len(controllers))
    traj = simulate(robot, stack, batch, SimConfig(period_s=1e-3, substeps=2))
    per_law = {}
    for i, name in enumerate(law_names):
        rows = range(i * len(conditions), (i + 1) * len(conditions))
        first = None
        for b in rows:
            over = np.argwhere(~np.isfinite(traj.qd[b]) | (np.abs(traj.qd[b]) > robot.velocity_limit_rad_s))
            if len(over) and first is None:
                first = {"t_s": round(float(traj.t_s[over[0][0]]), 4), "joint": robot.joint_names[over[0][1]]}
        per_law[name] = {
            "within_limits": int(traj.within_limits[list(rows)].sum()),
            "position_ratio_max": round(float(traj.position_ratio[list(rows)].max()), 2),
            "velocity_ratio_max": round(float(traj.velocity_ratio[list(rows)].max()), 2),
            "first_velocity_violation": first,
        }
    return {"wall_s": round(time.perf_counter() - started, 1), "per_law": per_law}


def sweep(robot: Any, conditions: list[Any], deployable: dict[str, Any]) -> dict[str, Any]:
    """PD's HMPC under other rate bounds and previews (module docstring)."""
    one_ms = {**deployable, "prediction_step_s": 1e-3}
    runs: dict[str, Any] = {}
    for rate_nm_s in (1000.0, 3000.0, 10000.0):
        bounded = replace(robot, torque_rate_limit_nm_s=np.full(robot.n_joints, rate_nm_s))
        runs[f"rate {rate_nm_s:g} N·m/s, 1 ms steps"] = variant(bounded, conditions, one_ms, ("pd",))
    runs["robot's rate, 5 ms steps"] = variant(robot, conditions, {**one_ms, "prediction_step_s": 5e-3}, ("pd",))
    runs["robot's rate, 20 steps of 1 ms"] = variant(robot, conditions, {**one_ms, "horizon_steps": 20}, ("pd",))
    smooth = {**one_ms, "rate_weight_scale": 10 * float(one_ms["rate_weight_scale"])}
    runs["robot's rate, 1 ms steps, 10x smoothness"] = variant(robot, conditions, smooth, ("pd",))
    return {"robot": robot.name, "torque_rate_nm_s": robot.torque_rate_nm_s.tolist(), "pd": runs}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="ur5")
    parser.add_argument("--conditions", type=int, default=1)
    parser.add_argument("--duration-s", type=float, default=2.4)
    parser.add_argument("--sweep", action="store_true", help="PD only: rate bound x prediction step (docstring)")
    args = parser.parse_args()
    robot = load_robot(args.robot)
    seed = StructuredConfig().train_seed
    conditions = paper_range_conditions(robot, args.conditions, seed, prefix="T")
    conditions = [replace(c, duration_s=args.duration_s) for c in conditions]
    deployable = formulation_options("deployable", robot.name)
    if args.sweep:
        print(json.dumps(sweep(robot, conditions, deployable), indent=1))
        return
    out = {
        "robot": robot.name,
        "torque_rate_nm_s": robot.torque_rate_nm_s.tolist(),
        "prediction_step_s": deployable.get("prediction_step_s", 1e-3),
        "conditions": [c.name for c in conditions],
        "duration_s": args.duration_s,
        "deployable": variant(robot, conditions, deployable),
        "deployable_without_rate_bound": variant(robot, conditions, {**deployable, "torque_rate_limit": "none"}),
        "deployable_1ms_prediction_step": variant(robot, conditions, {**deployable, "prediction_step_s": 1e-3}),
        "machine": benchinfo.machine(),
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
