"""``hil experiment --plant hil``'s table.md and parity plots: Table II's layout with the paper's
values beside, then the parity table; the score difference per law and mode as figures."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from models.effort import format_effort_table
from models.feedback import LAW_TITLES

#: The paper's Table II (hardware): FB score -> LMPC score per law.
PAPER_TABLE_II: dict[str, tuple[float, float]] = {
    "pd": (0.997, 0.661),
    "pid": (0.728, 0.246),
    "adrc": (0.278, 0.124),
    "hinf": (0.234, 0.090),
    "smc": (0.245, 0.007),
    "mrac": (0.046, 0.013),
}


def format_hil_table(results: dict[str, Any]) -> str:
    """Table II's layout (FB -> LMPC per law, the paper's beside), then the parity table."""
    modes = results["config"]["modes"]
    hil = results["hil"]
    times = " | ".join(f"t_{'L' if m == 'lmpc' else 'FB'} (µs)" for m in modes)
    eta = " | η_L (%)" if {"fb", "lmpc"} <= set(modes) else ""
    lines = ["| Controller | " + " | ".join(m.upper() for m in modes) + eta + " | paper FB → LMPC | " + times + " |"]
    lines.append("|" + "---|" * (lines[0].count("|") - 1))
    for law, row in results["table"].items():
        cells = [LAW_TITLES.get(law, law)]
        for mode in modes:
            failed = row[mode].get("failed_conditions", [])
            cells.append(f"{row[mode]['score']:.3f}" + (f" ✗{len(failed)}" if failed else ""))
        if "eta" in row.get("lmpc", {}):
            bad = row["lmpc"].get("failed_conditions") or row["fb"].get("failed_conditions")
            cells.append("—" if bad else f"{100 * row['lmpc']['eta']:.1f}")
        paper = PAPER_TABLE_II.get(law)
        cells.append(f"{paper[0]:.3f} → {paper[1]:.3f}" if paper else "—")
        cells += [f"{row[m]['time_per_cycle']['median_ms'] * 1e3:.1f}" for m in modes]
        lines.append("| " + " | ".join(cells) + " |")
    limits = "yes" if results["all_runs_finite_and_within_limits"] else "NO (see results.json runs)"
    clock = "free-running (both on the wall clock)" if hil.get("clock") == "realtime" else "lock-stepped"
    invalid = hil.get("invalid_runs") or []
    lines += [
        "",
        f"HIL: the runtime (hil_runtime) drives the pybullet target over CAN ({hil['transport']} transport), "
        f"{clock} at {hil['period_s'] * 1e3:g} ms, {hil['target_substeps']} physics substeps per period; "
        f"{hil['simulated_s']:g} s simulated in {hil['wall_s']:g} s. Robot {results['robot']}; conditions: "
        f"{', '.join(c['name'] for c in results['conditions'])}; gain set '{results['config']['gain_set']}'.",
        "Scores: the simulation's composite (docs/scoring.md), normalized per condition among the runs of this "
        "table. t: the runtime's compute per cycle (feedback in → set-points out), median.",
        f"Every run finite and inside the joint limits: {limits}. ✗k: k conditions faulted or left the limits.",
        "",
    ]
    if invalid:
        lines += [
            f"**INVALID** runs ({len(invalid)}; the plant fell behind real time, their scores are not valid and "
            "are counted in ✗k): "
            + "; ".join(f"{r['law']}/{r['mode']}/{r['condition']}: {r['invalid_reason']}" for r in invalid),
            "",
        ]
    lines += format_effort_table(results)
    if "parity" in results:
        lines += format_parity_table(results["parity"], modes)
    return "\n".join(lines)


def format_parity_table(parity_results: dict[str, Any], modes: list[str]) -> list[str]:
    head = ["Controller"]
    for mode in modes:
        m = mode.upper()
        head += [f"{m} sim", f"{m} HIL", f"{m} Δ (%)", f"{m} traj. RMS Δ (deg)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    worst = 0.0
    for law, row in parity_results["table"].items():
        cells = [LAW_TITLES.get(law, law)]
        for mode in modes:
            p = row[mode]
            failed = f" ✗{p['runs_failed']}" if p["runs_failed"] else ""
            if p["score_rel"] is None:  # every run of the row faulted or left the limits in a plant
                cells += ["—", "—", f"—{failed}", f"{p['trajectory_rms_diff_deg']:.4f}"]
                continue
            worst = max(worst, abs(p["score_rel"]))
            mark = "" if p["within_tolerance"] else " ⚠"
            cells += [
                f"{p['score_sim']:.3f}",
                f"{p['score_hil']:.3f}",
                f"{100 * p['score_rel']:+.1f}{mark}{failed}",
                f"{p['trajectory_rms_diff_deg']:.4f}",
            ]
        lines.append("| " + " | ".join(cells) + " |")
    tol = 100 * parity_results["tolerance"]
    return lines + [
        "",
        f"Parity: HIL vs the simulation (`hil experiment --modes {','.join(modes)}`, RK4, same conditions), both "
        "scored on the simulation's scale (its per-condition maxima), so a law's Δ is its own runs' difference, over "
        "the conditions on which both runs stayed inside the limits (✗k: k conditions faulted or left the limits in "
        "either plant, not compared; — none compared). "
        f"Largest |Δ| {100 * worst:.1f} % (budget {tol:g} %; ⚠ beyond it). Traj. RMS Δ: RMS over time and joints of "
        "q_HIL − q_sim, over the law's runs; docs/hil.md explains the differences.",
        "",
    ]


def plot_parity(
    results: dict[str, Any],
    trajectories: dict[tuple[str, str, str], dict[str, np.ndarray]],
    sim_traj_dir: Path,
    out_dir: Path,
) -> list[Path]:
    """Score difference per law and mode; per law, HIL vs simulation error on the worst condition."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from models.plots import save_figure

    out_dir.mkdir(parents=True, exist_ok=True)
    par = results["parity"]
    laws = list(par["table"])
    modes = results["config"]["modes"]
    written = []

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    width = 0.8 / len(modes)
    for i, mode in enumerate(modes):
        x = np.arange(len(laws)) + (i - (len(modes) - 1) / 2) * width
        rel = [par["table"][law][mode]["score_rel"] for law in laws]
        axes[0].bar(x, [np.nan if r is None else 100 * r for r in rel], width, label=mode.upper())
        axes[1].bar(x, [par["table"][law][mode]["trajectory_rms_diff_deg"] for law in laws], width, label=mode.upper())
    for ax, title in zip(axes, ("composite score, HIL vs sim (%)", "trajectory RMS difference (deg)"), strict=True):
        ax.set_xticks(np.arange(len(laws)), [LAW_TITLES.get(law, law) for law in laws])
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3, axis="y")
        ax.legend(fontsize=8)
    tol = 100 * par["tolerance"]
    axes[0].axhspan(-tol, tol, color="green", alpha=0.1)
    fig.tight_layout()
    path = out_dir / "parity_scores.png"
    written.append(save_figure(fig, path))

    for mode in modes:
        fig, axes = plt.subplots(len(laws), 1, figsize=(9, 1.9 * len(laws) + 0.6), sharex=True, squeeze=False)
        for ax, law in zip(axes[:, 0], laws, strict=True):
            mine = [p for p in par["runs"] if p["law"] == law and p["mode"] == mode]
            worst = max(mine, key=lambda p: abs(p["score_rel"]))
            cond = worst["condition"]
            h = trajectories[(law, mode, cond)]
            s = np.load(sim_traj_dir / f"{law}_{mode}_{cond}.npz")
            ax.plot(s["t"], np.abs(np.degrees(s["q_ref"] - s["q"])).mean(axis=1), lw=1, label="sim")
            ax.plot(h["t"], np.abs(np.degrees(h["q_ref"] - h["q"])).mean(axis=1), "--", lw=1, label="HIL")
            ax.plot(h["t"], np.abs(np.degrees(h["q"] - s["q"])).mean(axis=1), lw=0.8, color="k", label="|HIL − sim|")
            ax.set_yscale("log")
            ax.set_ylim(bottom=1e-5)
            ax.set_ylabel("deg", fontsize=8)
            ax.set_title(
                f"{LAW_TITLES.get(law, law)} {mode.upper()} {cond}: score Δ {100 * worst['score_rel']:+.1f} %",
                fontsize=9,
            )
            ax.grid(alpha=0.3, which="both")
        axes[0, 0].legend(fontsize=7, ncol=3)
        axes[-1, 0].set_xlabel("t (s)")
        fig.suptitle(f"{mode.upper()}: mean |e| over joints, HIL vs simulation (worst condition per law)", fontsize=10)
        fig.tight_layout()
        path = out_dir / f"parity_error_{mode}.png"
        written.append(save_figure(fig, path))
    return written


__all__ = ["PAPER_TABLE_II", "format_hil_table", "format_parity_table", "plot_parity"]
