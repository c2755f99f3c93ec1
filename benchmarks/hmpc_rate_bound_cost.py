"""What the torque-rate bound costs a law's HMPC on the paper's composite (docs/any_arm.md, "SMC on the real
arms"). One law, FB and HMPC on the robot's five default conditions (lock-step simulator, `ideal`), the
deployable formulation as the robot runs it and the same without its rate bound; each run normalizes FB and
HMPC between themselves (an ordering, not Table I's 18-configuration figure). Prints JSON.

    python benchmarks/hmpc_rate_bound_cost.py --robot ur5 --law smc
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any

import benchinfo

from models.cli.options import gain_set_for
from models.conditions import load_conditions
from models.experiment import ExperimentConfig, run_experiment
from models.hmpc.config import formulation_options
from models.robots import load_robot
from models.sim import SimConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robot", default="ur5")
    parser.add_argument("--law", default="smc")
    args = parser.parse_args()
    load = benchinfo.load_average()
    arm = load_robot(args.robot)
    conditions = load_conditions(None, robot=arm)
    config = ExperimentConfig(
        laws=(args.law,),
        modes=("fb", "hmpc"),
        gain_set=gain_set_for(arm.name, None),
        sim=SimConfig(),
        timing_cycles=20,
        save_trajectories=False,
        plots=False,
    )
    variants: dict[str, Any] = {}
    for name, limit in (("rate_bounded", None), ("unbounded", "none")):
        options = formulation_options("deployable", arm.name)
        if limit is not None:
            options["torque_rate_limit"] = limit
        with tempfile.TemporaryDirectory() as tmp:
            run_experiment(arm, conditions, config, Path(tmp), controller_options={"hmpc": options})
            data = json.loads((Path(tmp) / "results.json").read_text())
        table = data["table"][args.law]
        variants[name] = {
            "fb_score": round(table["fb"]["score"], 4),
            "hmpc_score": round(table["hmpc"]["score"], 4),
            "eta_h_pct": round(100 * table["hmpc"]["eta"], 1),
            "eta_h_effort_pct": round(100 * table["hmpc"]["eta_effort"], 1),
            "hmpc_deployable": sum(
                r["verdict"]["deployable"] for r in data["runs"] if r["mode"] == "hmpc" and r["law"] == args.law
            ),
        }
    print(
        benchinfo.report(
            "hmpc_rate_bound_cost",
            load,
            {"robot": arm.name, "law": args.law, "world": "lock-step simulator, ideal", "variants": variants},
        )
    )


if __name__ == "__main__":
    main()
