"""``run_demo``: the demo run end to end, what ``hil demo`` (models/cli/demo.py) calls: the options
checked, the HIL run watched live (models/demo/session.py says what runs where), its numbers beside
the simulation's (models/demo/analysis.py), the outputs (models/demo/report.py)."""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from models.demo.options import DemoOptions, realism_specs


def run_demo(options: DemoOptions, out_dir: Path, headless: bool = False, gui: bool = False) -> dict[str, Any]:
    """Run the demo end to end; write the outputs in ``out_dir``; return results.json's content."""
    from rich.console import Console

    from hil_runtime.outputs import prepare_output_dir
    from models.demo import analysis, report
    from models.demo.options import check_options, demo_condition
    from models.demo.session import run_hil
    from models.demo.view import ArmMirror, LiveView, check_display
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
    say_phases = headless or not console.is_terminal
    with LiveView(console, condition.duration_s, disturbance_s, say_phases, mirror) as view:
        outcome = run_hil(options, robot, condition, view.on_phase, view.tick)
    hil_wall_s = time.monotonic() - started

    console.print("hil demo: simulating the same bundle on the same condition (models simulator) ...", soft_wrap=True)
    steps = round(condition.duration_s / outcome.period_s)
    hil, coverage = analysis.hil_trajectory(outcome.record, steps, outcome.period_s)
    twin_realism = realism_specs(options)[1]
    sim, sim_wall_s = analysis.simulate_twin(
        robot, options.law, options.mode, condition, _bundle_gain_set(options), twin_realism
    )
    stats = analysis.final_stats(outcome)
    from sim_target.lateness import invalid_reason

    invalid = invalid_reason(outcome.target_lateness, outcome.period_s)
    recording = analysis.telemetry_recording(outcome)
    results: dict[str, Any] = {
        "demo": {
            **asdict(options),
            "duration_s": condition.duration_s,
            "disturbance_s": disturbance_s,
            "period_s": outcome.period_s,
            "bundle": str(_bundle_dir(options)),
            "steps": steps,
        },
        "fault": outcome.fault,
        # A free-running run whose plant fell behind the wall clock tests nothing: its scores are
        # not valid (sim_target/lateness.py). Lock-step runs have no wall clock to lag.
        "valid": invalid is None,
        "invalid_reason": invalid,
        "target": {"lateness": outcome.target_lateness, "realtime": outcome.target_realtime},
        "coverage": coverage,
        "scores": analysis.compare(robot, condition, hil, sim, outcome.fault),
        "timing": analysis.timing_figures(stats, outcome.record, outcome.period_s),
        "runtime_stats": stats,
        "telemetry": {"endpoint": outcome.endpoint, **analysis.telemetry_check(recording.arrays(), outcome.record)},
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
    title = (
        f"{options.law.upper()} {options.mode.upper()} on {condition.name}: tracking error, HIL (hil run + "
        f"pybullet target over the ipc bus) and simulation"
    )
    report.write_outputs(out_dir, results, outcome, recording, hil, sim, title, started)
    return results


def _bundle_dir(options: DemoOptions) -> Path:
    from models.demo.options import bundle_dir

    return bundle_dir(options)


def _bundle_gain_set(options: DemoOptions) -> str:
    manifest = json.loads((_bundle_dir(options) / "manifest.json").read_text())
    return str(manifest["law"].get("gain_set", "stabilized"))


__all__ = ["run_demo"]
