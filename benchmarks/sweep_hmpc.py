"""The HMPC weight sweep of issue 24: eta on the paper's and the effort-aware composite, chatter and the
deployable verdict vs the effort weight (W2a = c dt^2 / M_ii(0)^2 on the torque beyond the feed-forward)
and the smoothness weight (c_d dt^2 |M(q)^-1 (tau_j - tau_{j-1})|^2), under a realism profile, beside the
absolute (paper) and the anchored formulations. Prints JSON; writes the plot (docs/hmpc.md).

    python benchmarks/sweep_hmpc.py [--laws pd] [--realism realistic] [--effort 1 3 10 30 100]
        [--rate 0 1 100] [--duration-s 5] [--plot docs/figures/hmpc_weight_sweep.png] [--out FILE.json]

Each point is one ``run_experiment`` (FB and HMPC on the paper's five conditions, one seeded world).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import benchinfo
import numpy as np

from models.conditions import load_conditions
from models.experiment import ExperimentConfig, run_experiment
from models.hmpc.config import FORMULATIONS
from models.robots import load_robot

DEPLOYABLE = FORMULATIONS["deployable"]


def point(
    robot: Any, laws: tuple[str, ...], realism: str, label: str, options: dict[str, Any], duration_s: float = 5.0
) -> list[dict]:
    conditions = [replace(c, duration_s=duration_s) for c in load_conditions(None, robot=robot)]
    config = ExperimentConfig(
        laws=laws, modes=("fb", "hmpc"), timing_cycles=20, save_trajectories=False, plots=False, realism=realism
    )
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.monotonic()
        results = run_experiment(robot, conditions, config, Path(tmp), {"hmpc": options})
        print(f"{label}: {time.monotonic() - t0:.0f} s", file=sys.stderr)
    rows = []
    for law in laws:
        row = results["table"][law]["hmpc"]
        runs = [r for r in results["runs"] if r["law"] == law and r["mode"] == "hmpc"]
        fb_runs = [r for r in results["runs"] if r["law"] == law and r["mode"] == "fb"]
        rows.append(
            {
                "label": label,
                "options": options,
                "law": law,
                "eta": row.get("eta"),
                "eta_effort": row.get("eta_effort"),
                "deployable": sum(r["verdict"]["deployable"] for r in runs),
                "runs": len(runs),
                "within_limits": all(r["finite"] and r["within_limits"] for r in runs),
                "reasons": sorted({x.split(" ")[0] for r in runs for x in r["verdict"]["reasons"]}),
                "chatter_ratio": float(np.mean([r["effort"]["chatter_ratio"] for r in runs])),
                "chatter_shoulder_nm": float(np.mean([r["effort"]["chatter_nm"][1] for r in runs])),
                "fb_chatter_shoulder_nm": float(np.mean([r["effort"]["chatter_nm"][1] for r in fb_runs])),
                "rmse_deg": float(np.mean([r["metrics"]["rmse"] for r in runs])),
            }
        )
    return rows


def sweep(args: argparse.Namespace) -> dict[str, Any]:
    robot = load_robot("ur5_paper")
    laws = tuple(args.laws.split(","))
    started = time.monotonic()
    rows: list[dict] = []
    world, seconds = args.realism, args.duration_s
    for c in args.effort:
        rows += point(robot, laws, world, f"effort c={c:g}", {**DEPLOYABLE, "anchor_weight_scale": c}, seconds)
    for w in args.rate:
        rows += point(robot, laws, world, f"smoothness c_d={w:g}", {**DEPLOYABLE, "rate_weight_scale": w}, seconds)
    rows += point(robot, laws, world, "absolute (paper)", {}, seconds)
    rows += point(robot, laws, world, "anchored c=10", {"torque_cost": "anchored"}, seconds)
    rows += point(
        robot,
        laws,
        world,
        "anchored c=10 + smoothness + rate bound",
        {**DEPLOYABLE, "torque_cost": "anchored"},
        seconds,
    )
    return {
        "benchmark": "sweep_hmpc",
        "realism": args.realism,
        "laws": list(laws),
        "duration_s": seconds,
        "deployable_options": DEPLOYABLE,
        "rows": rows,
        "wall_s": round(time.monotonic() - started, 1),
        "machine": benchinfo.machine("numpy", "pin"),
        "command": "python " + " ".join(sys.argv),
    }


def plot(result: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, key, other, name in (
        (axes[0], "anchor_weight_scale", "rate_weight_scale", "effort weight c (W2a = c dt² / M_ii(0)²)"),
        (axes[1], "rate_weight_scale", "anchor_weight_scale", "smoothness weight c_d (c_d dt² |M⁻¹ Δτ|², 0 at 0.1)"),
    ):
        for law in result["laws"]:
            # the feed-forward family with the other weight at the shipped value, by this weight
            rows = sorted(
                (
                    r
                    for r in result["rows"]
                    if r["law"] == law
                    and r["options"].get("torque_cost") == "feedforward"
                    and r["options"].get(other) == DEPLOYABLE[other]
                ),
                key=lambda r: r["options"][key],
            )
            x = [max(r["options"][key], 0.1) for r in rows]
            ax.plot(x, [100 * (r["eta"] or np.nan) for r in rows], "o-", label=f"{law} η paper")
            ax.plot(x, [100 * (r["eta_effort"] or np.nan) for r in rows], "s--", label=f"{law} η effort")
            twin = ax.twinx()
            twin.plot(x, [r["chatter_shoulder_nm"] for r in rows], "^:", color="grey", label="chatter (shoulder)")
            twin.set_ylabel("shoulder chatter (N·m per cycle, RMS)")
            for xi, r in zip(x, rows, strict=True):
                ax.annotate(f"{r['deployable']}/{r['runs']}", (xi, 100 * (r["eta"] or 0.0)), fontsize=7)
        ax.set_xscale("log")
        ax.set_xlabel(name)
        ax.set_ylabel("η (%)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="lower left")
    fig.suptitle(f"HMPC under '{result['realism']}': η vs the weights (labels: deployable runs)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--laws", default="pd")
    parser.add_argument("--realism", default="realistic")
    parser.add_argument("--effort", type=float, nargs="*", default=[1.0, 3.0, 10.0, 30.0, 100.0])
    parser.add_argument("--rate", type=float, nargs="*", default=[0.0, 1.0, 100.0])
    parser.add_argument("--plot", type=Path, default=Path("docs/figures/hmpc_weight_sweep.png"))
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument(
        "--duration-s", type=float, default=5.0, help="each paper condition cut to this (impulse at 2 s)"
    )
    args = parser.parse_args()
    result = sweep(args)
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=1))
    plot(result, args.plot)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
