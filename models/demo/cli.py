"""``hil demo``: the product in one command (models/demo/session.py says what runs where)."""

from __future__ import annotations

import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from models.demo.session import BEST_LMPC_LAW, DEFAULT_CONDITION, DemoOptions, DemoPhase


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


def demo(
    law: Annotated[
        str, typer.Option(help=f"The bundle's law (default: the best LMPC law of Table I, {BEST_LMPC_LAW}).")
    ] = BEST_LMPC_LAW,
    mode: Annotated[str, typer.Option(help="lmpc: law + emulator (the bundle); fb: the law alone.")] = "lmpc",
    condition: Annotated[
        str, typer.Option(help="One of the paper's conditions, C1..C5 (each with its disturbance).")
    ] = DEFAULT_CONDITION,
    duration: Annotated[
        float | None, typer.Option(help="Seconds of the condition to run (default: all of it, 5 s).")
    ] = None,
    realtime: Annotated[
        bool,
        typer.Option(
            "--realtime",
            help="Free-running: the target on its own clock, the runtime on absolute deadlines (default: lock-step).",
        ),
    ] = False,
    headless: Annotated[bool, typer.Option("--headless", help="No live view (CI): the same run and outputs.")] = False,
    gui: Annotated[
        bool, typer.Option("--gui", help="Also open pybullet's viewer on the arm (needs a display).")
    ] = False,
    out: Annotated[Path, typer.Option(help="Output directory.")] = Path("results/demo"),
    target_substeps: Annotated[int, typer.Option(help="pybullet steps per control period.")] = 32,
) -> None:
    """Run the runtime (hil run) on the pybullet arm (hil target serve) as separate processes over the
    ipc CAN bus at 1 kHz, watch its telemetry live, stop everything, write the run and its scores."""
    from hil_runtime.outputs import remove_if_empty
    from models.demo.report import _LAW_TITLE

    options = DemoOptions(
        law=law.strip().lower(),
        mode=mode.strip().lower(),
        condition=condition.strip().upper(),
        duration_s=duration,
        realtime=realtime,
        target_substeps=target_substeps,
    )
    created = not out.exists()
    try:
        results = run_demo(options, out, headless=headless, gui=gui)
    except BaseException:
        if created:
            remove_if_empty(out)
        raise
    s, t = results["scores"], results["timing"]
    m_hil, m_sim = s["metrics"]["hil"], s["metrics"]["sim"]
    title = f"{_LAW_TITLE.get(options.law, options.law)} {options.mode.upper()} on {options.condition}"
    if results["fault"]:
        drives = "quick-stopped" if results["shutdown"].get("drives_stopped") else "not confirmed stopped"
        print(
            f"{title}: the runtime FAULTED after {t['cycles']} cycles ({results['fault']}); drives {drives}; "
            "the scores are not comparable with the simulation's"
        )
    else:
        print(
            f"{title}, {results['demo']['duration_s']:g} s: RMSE {m_hil['rmse']:.3f} deg (simulation "
            f"{m_sim['rmse']:.3f}), peak {m_hil['peak']:.3f} deg ({m_sim['peak']:.3f}), composite "
            f"{s['composite']['hil']:.3f} ({s['composite']['sim']:.3f})"
        )
    print(
        f"loop: {t['rate_hz']} Hz, {t['cycles']} cycles, overruns {t['overruns']}, period median/p99/max "
        f"{t['period_us']['median']}/{t['period_us']['p99']}/{t['period_us']['max']} µs, compute "
        f"{t['compute_us']['median']}/{t['compute_us']['p99']}/{t['compute_us']['max']} µs"
    )
    stop = results["shutdown"]
    clean = not (stop["processes_alive"] or stop["ipc_sockets_left"] or stop["control_sockets_left"])
    print(
        f"stopped: hil run exit {stop['runtime_exit_code']}, drives "
        f"{'quick-stopped' if stop.get('drives_stopped') else 'NOT confirmed stopped'}, target exit "
        f"{stop['target_exit_code']}, "
        + (
            "no process or socket left"
            if clean
            else f"processes left {stop['processes_alive']}, sockets left "
            f"{stop['ipc_sockets_left'] + stop['control_sockets_left']} (directory removed: {stop['work_dir_removed']})"
        )
    )
    print(
        f"wrote {out}/: run.npz, runtime_record.npz, simulation.npz, tracking_error.png, summary.md, results.json "
        f"({results['wall_s']['total_s']:g} s)"
    )
    if results["fault"]:
        from models.demo.processes import DemoError

        raise DemoError(f"the run faulted: {results['fault']} (outputs written to {out})")


def register(app: typer.Typer) -> None:
    app.command("demo")(demo)


__all__ = ["demo", "register", "run_demo"]
