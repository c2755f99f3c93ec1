"""``hil demo``: the runtime driving the emulated arm as separate processes, watched live (models/demo/)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from models.cli.options import RealismOption
from models.demo.session import BEST_LMPC_LAW, DEFAULT_CONDITION, DemoOptions


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
    target_substeps: Annotated[
        int | None,
        typer.Option(help="pybullet steps per control period (default: 32 lock-step, 4 --realtime; docs/target.md)."),
    ] = None,
    cpus: Annotated[
        str,
        typer.Option(help="--realtime: CPUs of the runtime's loop and the target's physics: auto, none or R,T."),
    ] = "auto",
    realism: RealismOption = "ideal",
    robot: Annotated[
        str,
        typer.Option(
            help="Robot: ur5_paper, ur5, panda, or a URDF path; its bundles models/bundles/<robot>/<law>/ "
            "(hil pipeline --robot) and its default condition (docs/any_arm.md)."
        ),
    ] = "ur5_paper",
) -> None:
    """Run the runtime (hil run) on the pybullet arm (hil target serve) as separate processes over the
    ipc CAN bus at 1 kHz, watch its telemetry live, stop everything, write the run and its scores."""
    from hil_runtime.outputs import remove_if_empty
    from models.demo.run import run_demo
    from models.feedback import LAW_TITLES

    options = DemoOptions(
        law=law.strip().lower(),
        mode=mode.strip().lower(),
        condition=condition.strip().upper(),
        duration_s=duration,
        realtime=realtime,
        target_substeps=target_substeps,
        cpus=cpus,
        realism=realism,
        robot=robot,
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
    title = f"{LAW_TITLES.get(options.law, options.law)} {options.mode.upper()} on {options.condition}"
    if results.get("invalid_reason"):
        print(f"{title}: INVALID run ({results['invalid_reason']}): its scores are not valid")
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
    from models.demo.report import target_line

    line = target_line(results.get("target") or {})
    if line is not None:
        print(line)
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
        from models.lab.processes import DemoError

        raise DemoError(f"the run faulted: {results['fault']} (outputs written to {out})")
