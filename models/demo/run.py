"""``run_demo``: the demo run end to end, what ``hil demo`` (models/cli/demo.py) calls; models/demo/session.py
says what runs where."""

from __future__ import annotations

import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from models.demo.session import DemoOptions, DemoPhase


def run_demo(options: DemoOptions, out_dir: Path, headless: bool = False, gui: bool = False) -> dict[str, Any]:
    """Run the demo end to end; write the outputs in ``out_dir``; return results.json's content."""
    from rich.console import Console
    from rich.live import Live

    from hil_runtime.outputs import atomic_path, prepare_output_dir, write_text_atomic
    from hil_runtime.telemetry.subscriber import save_record
    from models.demo import report
    from models.demo.session import check_options, demo_condition, run_hil
    from models.demo.view import ArmMirror, check_display, render
    from models.robots import load_robot

    check_options(options)
    if gui:
        check_display()
    robot = load_robot(options.robot)
    condition = demo_condition(options, robot)
    prepare_output_dir(out_dir, "--out")  # before any process starts: an unwritable --out fails now
    console = Console(stderr=True, highlight=False)
    disturbance_s = None if condition.disturbance is None else condition.disturbance.time_s
    started = time.monotonic()
    mirror = ArmMirror(robot.name) if gui else None
    shown = {"phase": DemoPhase(duration_s=condition.duration_s)}

    # Without a terminal (piped, a log file) a live view cannot redraw: say each phase instead.
    say_phases = headless or not console.is_terminal

    def on_phase(phase: DemoPhase) -> None:
        shown["phase"] = phase
        if say_phases:
            console.print(f"hil demo: {phase.text}", soft_wrap=True)

    def tick() -> None:
        if mirror is not None and shown["phase"].watch is not None:
            mirror.show(shown["phase"].watch)

    live = (
        None
        if say_phases
        else Live(get_renderable=lambda: render(shown["phase"], disturbance_s), console=console, refresh_per_second=8)
    )
    try:
        if live is not None:
            live.start()
        outcome = run_hil(options, robot, condition, on_phase, tick)
    finally:
        if live is not None:
            live.stop()
        if mirror is not None:
            mirror.close()
    hil_wall_s = time.monotonic() - started

    # --- the report: the simulation twin, the scores, the figures, the files -----------------------
    console.print("hil demo: simulating the same bundle on the same condition (models simulator) ...", soft_wrap=True)
    steps = round(condition.duration_s / outcome.period_s)
    hil, coverage = report.hil_trajectory(outcome.record, steps, outcome.period_s)
    sim, sim_wall_s = report.simulate_twin(robot, options.law, options.mode, condition, _bundle_gain_set(options))
    scores = report.compare(robot, condition, hil, sim, outcome.fault)
    stats = report.final_stats(outcome)
    recording = report.telemetry_recording(outcome)
    arrays = recording.arrays()
    bundle_dir = _bundle_dir(options)
    results: dict[str, Any] = {
        "demo": {
            **asdict(options),
            "duration_s": condition.duration_s,
            "disturbance_s": disturbance_s,
            "period_s": outcome.period_s,
            "bundle": str(bundle_dir),
            "steps": steps,
        },
        "fault": outcome.fault,
        "coverage": coverage,
        "scores": scores,
        "timing": report.timing_figures(stats, outcome.record, outcome.period_s),
        "runtime_stats": stats,
        "telemetry": {"endpoint": outcome.endpoint, **report.telemetry_check(arrays, outcome.record)},
        "shutdown": outcome.shutdown,
        "processes": outcome.processes,
        "wall_s": {
            **{k: round(v, 2) for k, v in outcome.wall_s.items()},
            "hil_total_s": round(hil_wall_s, 2),
            "simulation_s": round(sim_wall_s, 2),
        },
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "work_dir": outcome.work_dir,
    }
    logs = out_dir / "logs"
    logs.mkdir(exist_ok=True)
    for name, text in outcome.logs.items():
        write_text_atomic(logs / f"{name}.log", text)
    save_record(recording, out_dir / "run.npz", outcome.documents)
    with atomic_path(out_dir / "runtime_record.npz") as tmp:
        np.savez_compressed(tmp, **outcome.record)  # type: ignore[arg-type]  # numpy's stub types **kwds too narrowly
    with atomic_path(out_dir / "simulation.npz") as tmp:
        np.savez_compressed(tmp, **{k: v for k, v in sim.items() if k != "within_limits"})  # type: ignore[arg-type]  # as above
    title = (
        f"{options.law.upper()} {options.mode.upper()} on {condition.name}: tracking error, HIL (hil run + "
        f"pybullet target over the ipc bus) and simulation"
    )
    report.plot_tracking_error(
        hil, sim, list(outcome.schema.joints), title, disturbance_s, out_dir / "tracking_error.png"
    )
    results["wall_s"]["total_s"] = round(time.monotonic() - started, 2)
    results["files"] = [
        "run.npz",
        "runtime_record.npz",
        "simulation.npz",
        "tracking_error.png",
        "summary.md",
        "results.json",
        "logs/",
    ]
    summary = report.format_summary(results)
    write_text_atomic(out_dir / "summary.md", summary)
    report.write_json(out_dir / "results.json", results)  # last: its presence means the outputs are complete
    return results


def _bundle_dir(options: DemoOptions) -> Path:
    from models.lmpc.controller import bundle_path

    return bundle_path(options.robot, options.law, None)


def _bundle_gain_set(options: DemoOptions) -> str:
    import json

    return str(json.loads((_bundle_dir(options) / "manifest.json").read_text())["law"].get("gain_set", "stabilized"))


__all__ = ["run_demo"]
