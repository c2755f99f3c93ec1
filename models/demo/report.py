"""``hil demo``'s outputs: the recorded run, its scores beside the simulation's, the loop's timing.

    run.npz              the telemetry as the demo received it (``hil telemetry record``'s format:
                         one column per field, the schema, the runtime's config and bundle embedded)
    runtime_record.npz   the daemon's own per-cycle record (``hil run --record``): scored, complete
    tracking_error.png   per joint e = q_ref - q, HIL (the runtime on the target) and simulation
    summary.md           scores side by side, timing, the clean-stop checks
    results.json         everything above as numbers; written last (its presence: outputs complete)
    logs/                the target's and the daemon's own output

The numbers themselves (scores, timing, the telemetry check) are models/demo/analysis.py.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hil_runtime.outputs import atomic_path, json_safe, write_text_atomic
from models.feedback import LAW_TITLES
from models.scoring import METRICS

if TYPE_CHECKING:
    from models.demo.session import HilOutcome

OUTPUT_FILES = (
    "run.npz",
    "runtime_record.npz",
    "simulation.npz",
    "tracking_error.png",
    "summary.md",
    "results.json",
    "logs/",
)
_METRIC_TITLE = {
    "rmse": "RMSE (deg)",
    "mae": "MAE (deg)",
    "p95": "95th percentile of abs(e) (deg)",
    "peak": "peak abs(e) (deg)",
    "settle_s": "settling after the disturbance (s)",
    "dedt_rms": "RMS de/dt (deg/s)",
}


def plot_tracking_error(
    hil: dict[str, np.ndarray],
    sim: dict[str, np.ndarray],
    joints: list[str],
    title: str,
    disturbance_s: float | None,
    path: Path,
) -> Path:
    """Per joint e = q_ref - q (deg): the runtime on the target, and the simulator."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = hil["q"].shape[1]
    fig, axes = plt.subplots(n, 1, figsize=(9, 1.35 * n + 0.9), sharex=True, squeeze=False)
    e_hil = np.degrees(hil["q_ref"] - hil["q"])
    e_sim = np.degrees(sim["q_ref"] - sim["q"])
    for j, ax in enumerate(axes[:, 0]):
        ax.plot(hil["t"], e_hil[:, j], lw=1.1, color="C0", label="HIL: hil run on the pybullet target")
        ax.plot(sim["t"], e_sim[:, j], lw=0.8, color="k", ls="--", label="simulation")
        if disturbance_s is not None and disturbance_s <= hil["t"][-1]:
            ax.axvline(disturbance_s, color="C3", lw=0.8, ls=":", label="disturbance")
        ax.set_ylabel(f"{joints[j] if j < len(joints) else j}\n(deg)", fontsize=7)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
    axes[0, 0].legend(fontsize=7, ncol=3, loc="upper right")
    axes[-1, 0].set_xlabel("t (s)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return path


def target_line(target: dict[str, Any]) -> str | None:
    """The free-running target's lateness over the run, one line; None in lock-step."""
    late = target.get("lateness")
    if not late:
        return None
    rt = target.get("realtime") or {}
    return (
        f"target: {late['periods']} periods, late ticks {late['late_ticks']}, skipped {late['skipped_periods']} "
        f"({100 * late['skipped_fraction']:.3f} %), worst lag {late['worst_lag_s'] * 1e6:.0f} µs, physics thread "
        f"{100 * late['cpu_fraction']:.1f} % of a core ({rt.get('substeps', '?')} substeps; "
        f"{', '.join(rt.get('applied') or []) or 'no real-time setting'})"
    )


def _target_lines(target: dict[str, Any]) -> list[str]:
    line = target_line(target)
    return [] if line is None else ["", line[0].upper() + line[1:] + "."]


def format_summary(results: dict[str, Any]) -> str:
    demo, scores, timing, stop = results["demo"], results["scores"], results["timing"], results["shutdown"]
    law = LAW_TITLES.get(demo["law"], demo["law"])
    m_hil, m_sim = scores["metrics"]["hil"], scores["metrics"]["sim"]
    clock = "free-running in real time" if demo["realtime"] else "lock-stepped"
    disturbance = f" (disturbance at {demo['disturbance_s']:g} s)" if demo.get("disturbance_s") is not None else ""
    lines = [
        f"# hil demo: {law} {demo['mode'].upper()} on {demo['condition']}",
        "",
        (
            f"The runtime (`hil run`, bundle `{demo['bundle']}`) drove the pybullet UR5 (`hil target serve`) over "
            f"the ipc CAN bus, {clock} at {demo['period_s'] * 1e3:g} ms, for {demo['duration_s']:g} s of condition "
            f"{demo['condition']}{disturbance}."
        ),
        "",
    ]
    if results.get("invalid_reason"):
        lines += [
            f"**INVALID RUN**: {results['invalid_reason']}. The scores below are not valid HIL scores.",
            "",
        ]
    if results.get("fault"):
        lines += [
            (
                f"**The runtime FAULTED** after {timing['cycles']} cycles: {results['fault']}. The drives were "
                "quick-stopped; the HIL scores below are of a run held at its last pose from there, not comparable."
            ),
            "",
        ]
    lines += [
        "## Scores (smaller is better), beside the simulation of the same bundle and condition",
        "",
        "| metric | HIL | simulation | Δ (%) |",
        "|---|---|---|---|",
    ]
    for name in METRICS:
        rel = scores["relative"][name]
        shown = "—" if not math.isfinite(rel) else f"{100 * rel:+.1f}"
        lines.append(f"| {_METRIC_TITLE[name]} | {m_hil[name]:.4g} | {m_sim[name]:.4g} | {shown} |")
    comp = scores["composite"]
    shown = f"{100 * (comp['hil'] - comp['sim']) / comp['sim']:+.1f}" if comp["sim"] else "—"
    inside = {k: "yes" if v else "NO" for k, v in scores["within_limits"].items()}
    lines += [
        f"| composite (normalized between the two) | {comp['hil']:.3f} | {comp['sim']:.3f} | {shown} |",
        "",
        (
            f"Trajectory difference HIL − simulation: RMS {scores['trajectory_rms_diff_deg']:.4f} deg, max "
            f"{scores['trajectory_max_diff_deg']:.4f} deg. Inside the joint limits: HIL {inside['hil']}, simulation "
            f"{inside['sim']}. Cycles with the trust region's fallback: {scores['fallback_cycles']['hil']}."
        ),
        "",
        "## The loop (the runtime's own stats over the run)",
        "",
        "| figure | median | p99 | max |",
        "|---|---|---|---|",
    ]
    for name, key in (
        ("period (µs)", "period_us"),
        ("compute (µs)", "compute_us"),
        ("exchange on the bus (µs)", "exchange_us"),
    ):
        value = timing.get(key) or {}
        lines.append(f"| {name} | {value.get('median', '—')} | {value.get('p99', '—')} | {value.get('max', '—')} |")
    drives = (
        "all quick-stopped (Operation Enabled off)"
        if stop.get("drives_stopped")
        else str(stop.get("drives_operation_enabled_after_stop"))
    )
    lines += [
        "",
        (
            f"Rate {timing['rate_hz']} Hz over {timing['cycles']} cycles, overruns {timing['overruns']}, telemetry "
            f"{timing['telemetry_sent']} sent / {timing['telemetry_dropped']} dropped; received by the demo: "
            f"{results['telemetry']['samples']} states, {results['telemetry']['missing']} missing. Machine load "
            f"average {results['load_average']}."
        ),
        *_target_lines(results.get("target") or {}),
        "",
        "## Stop",
        "",
        (
            f"hil run: SIGTERM → exit {stop['runtime_exit_code']} in "
            f"{results['processes'].get('runtime', {}).get('stop_s')} s; drives afterwards: {drives}; target exit "
            f"{stop['target_exit_code']}; processes left {stop['processes_alive'] or 'none'}; ipc sockets left "
            f"{stop['ipc_sockets_left'] or 'none'}; private directory removed: "
            f"{'yes' if stop['work_dir_removed'] else 'NO'}."
        ),
        "",
    ]
    return "\n".join(lines)


def write_outputs(
    out_dir: Path,
    results: dict[str, Any],
    outcome: HilOutcome,
    recording: Any,  # hil_runtime.telemetry.subscriber.StateRecording
    hil: dict[str, np.ndarray],
    sim: dict[str, np.ndarray],
    plot_title: str,
    started: float,
) -> None:
    """Every file of the module docstring in ``out_dir``; results.json last. ``started`` (monotonic
    clock, the demo's start) dates ``wall_s.total_s``."""
    from hil_runtime.telemetry.subscriber import save_record

    logs = out_dir / "logs"
    logs.mkdir(exist_ok=True)
    for name, text in outcome.logs.items():
        write_text_atomic(logs / f"{name}.log", text)
    save_record(recording, out_dir / "run.npz", outcome.documents)
    simulation = {k: v for k, v in sim.items() if k != "within_limits"}
    # Any values: numpy's stub types savez_compressed's **kwds as also reaching its bool allow_pickle.
    records: tuple[tuple[str, dict[str, Any]], ...] = (
        ("runtime_record.npz", outcome.record),
        ("simulation.npz", simulation),
    )
    for name, arrays in records:
        with atomic_path(out_dir / name) as tmp:
            np.savez_compressed(tmp, **arrays)
    figure = out_dir / "tracking_error.png"
    plot_tracking_error(hil, sim, list(outcome.schema.joints), plot_title, results["demo"]["disturbance_s"], figure)
    results["wall_s"]["total_s"] = round(time.monotonic() - started, 2)
    results["files"] = list(OUTPUT_FILES)
    write_text_atomic(out_dir / "summary.md", format_summary(results))
    write_json(out_dir / "results.json", results)  # last: its presence means the outputs are complete


def write_json(path: Path, results: dict[str, Any]) -> None:
    write_text_atomic(path, json.dumps(json_safe(results), indent=2))


__all__ = ["OUTPUT_FILES", "format_summary", "plot_tracking_error", "write_json", "write_outputs"]
