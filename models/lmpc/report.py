"""Per-metric breakdown of an experiment's results.json (docs/lmpc.md): what moves eta.

    python -m models.lmpc.report results/experiment/results.json [--modes fb,hmpc,lmpc]

Prints, per law and mode, the six raw metrics averaged over the conditions (degrees, seconds), the
composite score and eta, and the ratio of each averaged metric to FB's; plus how many runs left the
limits. Raw metrics, so anyone can renormalize.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from models.feedback import LAW_TITLES

METRIC_TITLES = {
    "rmse": "RMSE (°)",
    "mae": "MAE (°)",
    "p95": "P95 (°)",
    "peak": "Peak (°)",
    "settle_s": "settling (s)",
    "dedt_rms": "dE/dt RMS (°/s)",
}


def breakdown(results: dict[str, Any], modes: tuple[str, ...] | None = None) -> str:
    """Markdown table: per law and mode, mean raw metrics over the conditions, score, eta, runs out of limits."""
    modes = modes or tuple(results["config"]["modes"])
    metrics = list(METRIC_TITLES)
    lines = [
        "| law | mode | " + " | ".join(METRIC_TITLES[m] for m in metrics) + " | score | η (%) | runs out of limits |",
        "|" + "---|" * (len(metrics) + 5),
    ]
    for law, row in results["table"].items():
        for mode in modes:
            runs = [r for r in results["runs"] if r["law"] == law and r["mode"] == mode]
            if not runs:
                continue
            means = {m: float(np.mean([r["metrics"][m] for r in runs])) for m in metrics}
            out = sum(1 for r in runs if not (r["finite"] and r["within_limits"]))
            eta = row[mode].get("eta")
            eta_text = "" if eta is None or row[mode].get("failed_conditions") else f"{100 * eta:.1f}"
            cells = [f"{means[m]:.3f}" for m in metrics]
            lines.append(
                f"| {LAW_TITLES.get(law, law)} | {mode} | "
                + " | ".join(cells)
                + f" | {row[mode]['score']:.3f} | {eta_text} | {out}/{len(runs)} |"
            )
    return "\n".join(lines)


def gain_kept(results: dict[str, Any]) -> dict[str, float | None]:
    """Per law: eta_L / eta_H (the share of the HMPC's gain the LMPC keeps), None where undefined."""
    out: dict[str, float | None] = {}
    for law, row in results["table"].items():
        eta_h, eta_l = row.get("hmpc", {}).get("eta"), row.get("lmpc", {}).get("eta")
        failed = any(row.get(m, {}).get("failed_conditions") for m in ("fb", "hmpc", "lmpc"))
        out[law] = None if failed or eta_h in (None, 0) or eta_l is None else float(eta_l / eta_h)
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("results", type=Path)
    parser.add_argument("--modes", default=None)
    args = parser.parse_args()
    results = json.loads(args.results.read_text())
    modes = tuple(args.modes.split(",")) if args.modes else None
    print(breakdown(results, modes))
    kept = gain_kept(results)
    if any(v is not None for v in kept.values()):
        print(
            "\nshare of the HMPC's gain kept (eta_L / eta_H): "
            + ", ".join(f"{LAW_TITLES.get(k, k)} {v:.2f}" for k, v in kept.items() if v is not None)
        )


if __name__ == "__main__":
    main()
