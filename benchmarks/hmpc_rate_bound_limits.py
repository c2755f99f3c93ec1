"""Does the deployable HMPC (the structured pipeline's expert) stay inside a robot's limits? Per law,
on the pipeline's first training condition (paper-range draw, seed 7101, the robot's default
disturbance), the largest position and velocity ratio to the limits: the formulation as the robot runs
it (its torque-rate bound, models.hmpc.config.formulation_options), without the rate bound, and with
the bound but predicting in control-period steps (docs/any_arm.md, "Torque-rate bound"). Prints JSON.

    python benchmarks/hmpc_rate_bound_limits.py --robot ur5 [--conditions 1] [--duration-s 2.4]
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


def variant(robot: Any, conditions: list[Any], options: dict[str, Any]) -> dict[str, Any]:
    """Every law's HMPC side by side on ``conditions``: per law the worst ratios and the first violation."""
    laws = [make_law(name, robot, 1e-3, "designed") for name in LAW_NAMES]
    controllers = [make_hmpc_controller(law, robot, **options) for law in laws]
    started = time.perf_counter()
    batch = [c for _ in controllers for c in conditions]
    stack = ControllerStack(controllers, [len(conditions)] * len(controllers))
    traj = simulate(robot, stack, batch, SimConfig(period_s=1e-3, substeps=2))
    per_law = {}
    for i, name in enumerate(LAW_NAMES):
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="ur5")
    parser.add_argument("--conditions", type=int, default=1)
    parser.add_argument("--duration-s", type=float, default=2.4)
    args = parser.parse_args()
    robot = load_robot(args.robot)
    seed = StructuredConfig().train_seed
    conditions = paper_range_conditions(robot, args.conditions, seed, prefix="T")
    conditions = [replace(c, duration_s=args.duration_s) for c in conditions]
    deployable = formulation_options("deployable", robot.name)
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
