"""The noise sweep of issue 23: eta and chatter vs encoder noise, every law and mode, on the models
simulator under a realism profile whose encoder noise is swept. Prints JSON; writes the plot and the
markdown table (docs/realism.md, README).

    python benchmarks/bench_realism.py [--noise-rad 0 1e-5 3e-5 1e-4 3e-4] [--base ideal|realistic]
        [--laws pd,pid,adrc,hinf,smc,mrac] [--modes fb,hmpc,lmpc] [--conditions C1] [--duration-s 3]
        [--plot docs/figures/realism_noise_sweep.png] [--table FILE.md]

Base ``ideal``: the ideal world with the velocity reported as drives do (finite difference of the
noisy position), so the only change along the sweep is the noise. Base ``realistic``: the realistic
profile with its encoder noise replaced. Each noise level is one ``run_experiment`` (every law and
mode on the same noise sequence: one seed), so eta compares the laws' modes on one world.
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
import yaml

from models.conditions import load_conditions
from models.experiment import ExperimentConfig, run_experiment
from models.feedback import LAW_TITLES
from models.hmpc.config import FORMULATIONS
from models.robots import load_robot
from sim_target.realism_profiles import profile_path


def profile_file(base: str, noise_rad: float, into: Path) -> Path:
    data: dict[str, Any] = yaml.safe_load(profile_path(base).read_text()) or {}
    sensing = dict(data.get("sensing", {}))
    sensing["encoder_noise_rad"] = noise_rad
    sensing["velocity"] = "difference"
    data["sensing"] = sensing
    path = into / f"{base}_noise_{noise_rad:g}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def sweep(args: argparse.Namespace) -> dict[str, Any]:
    robot = load_robot("ur5_paper")
    names = [c.strip().upper() for c in args.conditions.split(",")]
    conditions = [c for c in load_conditions(None, robot=robot) if c.name in names]
    conditions = [replace(c, duration_s=args.duration_s) for c in conditions]
    laws = tuple(args.laws.split(","))
    modes = tuple(args.modes.split(","))
    points = []
    started = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        for noise in args.noise_rad:
            path = profile_file(args.base, noise, Path(tmp))
            config = ExperimentConfig(
                laws=laws, modes=modes, timing_cycles=20, save_trajectories=False, plots=False, realism=str(path)
            )
            t0 = time.monotonic()
            # the HMPC as `hil experiment` runs it (its default formulation, docs/hmpc.md), not the bare
            # ExperimentConfig's absolute-cost one
            options = {"hmpc": dict(FORMULATIONS[args.hmpc_formulation])}
            results = run_experiment(
                robot, conditions, config, Path(tmp) / f"out_{noise:g}", controller_options=options
            )
            print(f"noise {noise:g} rad: {time.monotonic() - t0:.0f} s", file=sys.stderr)
            for law in laws:
                for mode in modes:
                    row = results["table"][law][mode]
                    runs = [r for r in results["runs"] if r["law"] == law and r["mode"] == mode]
                    points.append(
                        {
                            "noise_rad": noise,
                            "law": law,
                            "mode": mode,
                            "eta": row.get("eta"),
                            "eta_effort": row.get("eta_effort"),
                            "score": row["score"],
                            "score_effort": row["score_effort"],
                            "within_limits": all(r["finite"] and r["within_limits"] for r in runs),
                            "deployable": all(r["verdict"]["deployable"] for r in runs),
                            "reasons": sorted({x.split(" ")[0] for r in runs for x in r["verdict"]["reasons"]}),
                            # the shoulder lift (joint 2), the measurement, and the worst joint
                            "chatter_shoulder_nm": float(np.mean([r["effort"]["chatter_nm"][1] for r in runs])),
                            "chatter_max_ratio_of_limit": float(
                                max(max(np.asarray(r["effort"]["chatter_nm"]) / robot.torque_limit_nm) for r in runs)
                            ),
                            "rmse_deg": float(np.mean([r["metrics"]["rmse"] for r in runs])),
                        }
                    )
    return {
        "benchmark": "bench_realism",
        "base_profile": args.base,
        "conditions": names,
        "duration_s": args.duration_s,
        "noise_rad": list(args.noise_rad),
        "points": points,
        "wall_s": round(time.monotonic() - started, 1),
        "machine": benchinfo.machine("numpy", "pin"),
        "command": "python " + " ".join(sys.argv),
    }


def merge(paths: list[Path]) -> dict[str, Any]:
    """One result from sweeps over disjoint noise levels (same laws, modes, conditions, base)."""
    parts = [json.loads(p.read_text()) for p in paths]
    first = parts[0]
    for part in parts[1:]:
        for key in ("base_profile", "conditions", "duration_s"):
            if part[key] != first[key]:
                raise SystemExit(f"--merge: {key} differs between the files")
    noises = sorted(n for part in parts for n in part["noise_rad"])
    return {
        **first,
        "noise_rad": noises,
        "points": [p for part in parts for p in part["points"]],
        "wall_s": sum(part["wall_s"] for part in parts),
        "command": [part["command"] for part in parts],
    }


def table(result: dict[str, Any]) -> str:
    noises = result["noise_rad"]
    head = ["law", "mode", *[f"σ={n:g}" for n in noises]]
    lines = [
        "Each cell: η on the paper's composite (%) / η effort-aware (%) / shoulder-lift chatter (N·m) / "
        "deployable (✓, ✗; ✗L: left the limits). FB rows: chatter and verdict only.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    by = {(p["law"], p["mode"], p["noise_rad"]): p for p in result["points"]}
    laws = sorted({p["law"] for p in result["points"]}, key=[p["law"] for p in result["points"]].index)
    modes = sorted({p["mode"] for p in result["points"]}, key=[p["mode"] for p in result["points"]].index)
    for law in laws:
        for mode in modes:
            cells = [LAW_TITLES.get(law, law), mode.upper()]
            for n in noises:
                p = by[(law, mode, n)]
                verdict = "✓" if p["deployable"] else ("✗L" if not p["within_limits"] else "✗")
                chatter = f"{p['chatter_shoulder_nm']:.3g}"
                if p["eta"] is None:
                    cells.append(f"{chatter} {verdict}")
                else:
                    fb = by.get((law, "fb", n))
                    defined = p["within_limits"] and (fb is None or fb["within_limits"])  # η against a failed FB: —
                    eta = f"{100 * p['eta']:.0f}" if defined else "—"
                    eff = f"{100 * p['eta_effort']:.0f}" if defined else "—"
                    cells.append(f"{eta} / {eff} / {chatter} {verdict}")
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(result: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from models.plots import save_figure

    points = result["points"]
    laws = list(dict.fromkeys(p["law"] for p in points))
    modes = list(dict.fromkeys(p["mode"] for p in points))
    noises = np.asarray(result["noise_rad"], float)
    x = np.where(noises > 0, noises, noises[noises > 0].min() / 3 if (noises > 0).any() else 1e-6)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    styles = {"fb": ":", "hmpc": "--", "lmpc": "-"}
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, law in enumerate(laws):
        for mode in modes:
            mine = sorted((p for p in points if p["law"] == law and p["mode"] == mode), key=lambda p: p["noise_rad"])
            kw = {"color": colors[i % len(colors)], "ls": styles.get(mode, "-"), "lw": 1.2}
            label = f"{LAW_TITLES.get(law, law)} {mode.upper()}"
            axes[0].plot(x, [p["chatter_shoulder_nm"] for p in mine], label=label, marker=".", **kw)
            if mode != "fb":
                fb_ok = {p["noise_rad"]: p["within_limits"] for p in points if p["law"] == law and p["mode"] == "fb"}
                ok = [p["within_limits"] and p["eta"] is not None and fb_ok.get(p["noise_rad"], True) for p in mine]
                eta = [100 * p["eta"] if good else np.nan for p, good in zip(mine, ok, strict=True)]
                eff = [100 * p["eta_effort"] if good else np.nan for p, good in zip(mine, ok, strict=True)]
                axes[1].plot(x, eta, marker=".", **kw)
                axes[2].plot(x, eff, marker=".", **kw)
    axes[0].set_yscale("log")
    axes[0].set_title("chatter, shoulder lift (N·m RMS per cycle)", fontsize=10)
    axes[1].set_title("η, paper's composite (%) (gaps: left the limits)", fontsize=10)
    axes[2].set_title("η, effort-aware composite (%)", fontsize=10)
    for ax in axes:
        ax.set_xscale("log")
        ax.set_xlabel("encoder noise σ (rad); leftmost point: σ = 0")
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=6, ncol=2)
    fig.suptitle(
        f"Noise sweep on the models simulator, base profile '{result['base_profile']}', "
        f"{','.join(result['conditions'])}, {result['duration_s']:g} s (benchmarks/bench_realism.py)",
        fontsize=10,
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise-rad", type=float, nargs="+", default=[0.0, 1e-5, 3e-5, 1e-4, 3e-4])
    parser.add_argument("--base", default="ideal", choices=["ideal", "realistic", "harsh"])
    parser.add_argument("--laws", default="pd,pid,adrc,hinf,smc,mrac")
    parser.add_argument("--modes", default="fb,hmpc,lmpc")
    parser.add_argument(
        "--hmpc-formulation", default="deployable", choices=sorted(FORMULATIONS), help="as `hil experiment`'s"
    )
    parser.add_argument("--conditions", default="C1")
    parser.add_argument("--duration-s", type=float, default=3.0)  # through the disturbance at 2 s
    parser.add_argument("--plot", type=Path, default=None)
    parser.add_argument("--table", type=Path, default=None)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument(
        "--merge",
        type=Path,
        nargs="+",
        default=None,
        help="JSON files of sweeps run apart (e.g. noise levels split "
        "over processes): one table and plot from them, no new runs",
    )
    args = parser.parse_args()
    result = merge(args.merge) if args.merge else sweep(args)
    text = json.dumps(result, indent=2)
    print(text)
    if args.json is not None:
        args.json.write_text(text)
    if args.table is not None:
        args.table.write_text(table(result))
    if args.plot is not None:
        plot(result, args.plot)


if __name__ == "__main__":
    main()
