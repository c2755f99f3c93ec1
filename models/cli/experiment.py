"""``hil experiment``: laws x modes x conditions on the simulator or the HIL plant (Table I, Table II)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, cast

import typer

from models.cli.options import GainsOption, RealismOption, RobotOption, gain_set_for, one_of, positive, split_names

if TYPE_CHECKING:  # imported where used: the CLI starts without the HIL experiment's imports
    from models.hil_experiment import HilOptions
    from sim_target.launch import Transport


def experiment(
    laws: Annotated[str, typer.Option(help="Comma-separated feedback laws.")] = "pd,pid,adrc,hinf,smc,mrac",
    modes: Annotated[
        str | None,
        typer.Option(help="Comma-separated modes: fb, hmpc, lmpc (default: fb,hmpc,lmpc; with --plant hil: fb,lmpc)."),
    ] = None,
    conditions: Annotated[
        str | None,
        typer.Option(
            help="Conditions YAML (default: the robot's five: the paper's for ur5_paper), random:COUNT:SEED "
            "(seeded, the paper's range) or envelope:COUNT:SEED (seeded, the whole envelope: offsets, sines, "
            "holds, random disturbance times)."
        ),
    ] = None,
    robot: RobotOption = "ur5_paper",
    out: Annotated[Path, typer.Option(help="Output directory (checked writable before any work).")] = Path(
        "results/experiment"
    ),
    mismatch: Annotated[str, typer.Option(help="'none', or 'paper': +0.5 kg payload, inertias ±20 %.")] = "none",
    gains: GainsOption = None,
    period_s: Annotated[float, typer.Option(help="Control period (s).")] = 1e-3,
    substeps: Annotated[int, typer.Option(help="RK4 plant steps per control period.")] = 2,
    plant_backend: Annotated[str, typer.Option(help="Plant dynamics: pinocchio or rne (own RNEFDA).")] = "pinocchio",
    timing_cycles: Annotated[int, typer.Option(help="Single-robot cycles timed per law and mode.")] = 1000,
    no_trajectories: Annotated[bool, typer.Option("--no-trajectories", help="Skip the .npz files.")] = False,
    no_plots: Annotated[bool, typer.Option("--no-plots", help="Skip the PNG plots.")] = False,
    lmpc_bundles: Annotated[Path | None, typer.Option(help="LMPC bundle root (default: the shipped ones).")] = None,
    hmpc_formulation: Annotated[
        str,
        typer.Option(
            help="HMPC formulation: 'absolute' (W2 on tau), 'anchored' (W2 on tau - w* tau_fb) or 'deployable' "
            "(W2 on tau - ID(q, qd, qdd_d), smoothness on tau_j - tau_(j-1), libfranka's rate bound; the default, "
            "the HMPC the shipped LMPC imitates; docs/hmpc.md)."
        ),
    ] = "deployable",
    hmpc_prediction_step_s: Annotated[
        float | None, typer.Option(help="HMPC prediction step (s); default: the control period.")
    ] = None,
    hmpc_anchor_scale: Annotated[
        float, typer.Option(help="Anchored cost: c in W2_i = c h^2 / M_ii(0)^2, h the prediction step.")
    ] = 10.0,
    plant: Annotated[
        str,
        typer.Option(
            help="sim: the models simulator; hil: the runtime drives the pybullet target over CAN (docs/hil.md)."
        ),
    ] = "sim",
    transport: Annotated[
        str, typer.Option(help="--plant hil: virtual (one process), ipc or bridge (the target in its own process).")
    ] = "virtual",
    target_substeps: Annotated[
        int | None,
        typer.Option(help="--plant hil: pybullet steps per control period (default: 32 lock-step, 8 real time)."),
    ] = None,
    realism: RealismOption = "ideal",
    clock: Annotated[
        str,
        typer.Option(
            help="--plant hil: lockstep (each SYNC steps the arm) or realtime (both free-running; needs "
            "--transport ipc or bridge; runs whose plant fell behind are INVALID)."
        ),
    ] = "lockstep",
    cpus: Annotated[
        str,
        typer.Option(help="--plant hil --clock realtime: the runtime loop's and the target's CPUs: auto, none, R,T."),
    ] = "auto",
    no_parity: Annotated[
        bool,
        typer.Option("--no-parity", help="--plant hil: skip the simulation twin and the HIL-vs-simulation comparison."),
    ] = False,
    torque_rate_limit: Annotated[
        str,
        typer.Option(
            help="LMPC output rate limit, sim and hil alike: none, or libfranka (each joint's torque change per "
            "cycle clamped to the bundle's torque-rate bound, as franka::limitRate; docs/lmpc.md section 10)."
        ),
    ] = "none",
    lmpc_velocity_filter_hz: Annotated[
        float | None,
        typer.Option(
            help="LMPC velocity input filter, sim and hil alike: a first-order low-pass at this cutoff (Hz) on the "
            "measured velocity before the policy (bundle.velocity_filter_hz; docs/lmpc.md section 13); default off."
        ),
    ] = None,
) -> None:
    """Run laws x modes x conditions; write results.json, table.md, trajectories and plots."""
    from hil_runtime.outputs import prepare_output_dir, remove_if_empty
    from models.feedback import LAW_NAMES
    from models.modes import MODES

    law_list = split_names(laws, LAW_NAMES, "laws")
    one_of(plant, ("sim", "hil"), "--plant")
    from hil_runtime.rate_limit import TORQUE_RATE_LIMITS

    one_of(torque_rate_limit, TORQUE_RATE_LIMITS, "--torque-rate-limit")
    if lmpc_velocity_filter_hz is not None:
        from hil_runtime.velocity_filter import filter_pole
        from models.errors import ModelInputError

        try:
            filter_pole(lmpc_velocity_filter_hz, period_s)
        except ValueError as exc:
            raise ModelInputError(f"--lmpc-velocity-filter-hz: {exc}") from None
    default_modes = "fb,lmpc" if plant == "hil" else "fb,hmpc,lmpc"
    mode_list = split_names(modes if modes is not None else default_modes, MODES, "modes")
    hil: HilOptions | None = None
    if plant == "hil":
        from models.hil_experiment import HilOptions
        from sim_target.config import LOCKSTEP_SUBSTEPS, REALTIME_SUBSTEPS

        if target_substeps is None:
            target_substeps = REALTIME_SUBSTEPS if clock == "realtime" else LOCKSTEP_SUBSTEPS
        positive(target_substeps, "--target-substeps", integer=True)
        hil = HilOptions(
            transport=cast("Transport", transport),  # checked (one line, exit 2) by check_hil_inputs
            target_substeps=target_substeps,
            parity=not no_parity,
            clock=clock,
            cpus=cpus,
            bundle_dir=lmpc_bundles,
            torque_rate_limit=torque_rate_limit,
            velocity_filter_hz=lmpc_velocity_filter_hz,
        )
    one_of(mismatch, ("none", "paper"), "--mismatch")
    positive(period_s, "--period-s")
    positive(substeps, "--substeps", integer=True)
    positive(timing_cycles, "--timing-cycles", integer=True)
    if hmpc_prediction_step_s is not None:
        positive(hmpc_prediction_step_s, "--hmpc-prediction-step-s")
    positive(hmpc_anchor_scale, "--hmpc-anchor-scale")
    one_of(plant_backend, ("pinocchio", "rne"), "--plant-backend")
    from models.hmpc.config import FORMULATIONS

    one_of(hmpc_formulation, tuple(FORMULATIONS), "--hmpc-formulation")
    from models.robots import load_robot

    gains = gain_set_for(load_robot(robot).name, gains)  # a bad robot or gain set: one line before any work
    created = not out.exists()
    prepare_output_dir(out, "--out")  # before any work: a read-only or blocked --out fails now, not after minutes
    try:
        _experiment(
            law_list,
            mode_list,
            conditions,
            robot,
            out,
            mismatch,
            gains,
            period_s,
            substeps,
            plant_backend,
            timing_cycles,
            no_trajectories,
            no_plots,
            lmpc_bundles,
            hmpc_formulation,
            hmpc_prediction_step_s,
            hmpc_anchor_scale,
            hil,
            realism,
            torque_rate_limit,
            lmpc_velocity_filter_hz,
        )
    except BaseException:
        if created:
            remove_if_empty(out)  # nothing was written: leave no empty directory behind
        raise


def _experiment(
    law_list: tuple[str, ...],
    mode_list: tuple[str, ...],
    conditions: str | None,
    robot: str,
    out: Path,
    mismatch: str,
    gains: str,
    period_s: float,
    substeps: int,
    plant_backend: str,
    timing_cycles: int,
    no_trajectories: bool,
    no_plots: bool,
    lmpc_bundles: Path | None,
    hmpc_formulation: str,
    hmpc_prediction_step_s: float | None,
    hmpc_anchor_scale: float,
    hil: HilOptions | None = None,
    realism: str = "ideal",
    torque_rate_limit: str = "none",
    velocity_filter_hz: float | None = None,
) -> None:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from models.conditions import load_conditions
    from models.experiment import PAPER_MISMATCH, ExperimentConfig, run_experiment
    from models.robots import load_robot
    from models.sim import SimConfig

    arm = load_robot(robot)
    from models.envelope_conditions import envelope_conditions, parse_envelope_spec
    from models.lmpc.paper_range import paper_range_conditions, parse_random_spec

    spec = parse_random_spec(conditions) if conditions is not None else None
    envelope = parse_envelope_spec(conditions) if conditions is not None else None
    if spec is not None:
        condition_list = paper_range_conditions(arm, *spec)
    elif envelope is not None:
        condition_list = envelope_conditions(arm, *envelope)
    else:
        condition_list = load_conditions(None if conditions is None else Path(conditions), robot=arm)
    if mismatch == "paper":
        condition_list = [replace(c, mismatch=PAPER_MISMATCH) for c in condition_list]
    config = ExperimentConfig(
        laws=law_list,
        modes=mode_list,
        gain_set=gains,
        sim=SimConfig(period_s=period_s, substeps=substeps, plant_backend=plant_backend),
        timing_cycles=timing_cycles,
        save_trajectories=not no_trajectories,
        plots=not no_plots,
        realism=realism,
    )
    from models.experiment import realism_spec

    realism_spec(config, arm)  # a bad profile: one line, exit 2, before any work
    console = Console(stderr=True)
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, console=console) as bar:

        def progress(label: str, total: int) -> Callable[[int], None]:
            task = bar.add_task(label, total=total)
            return lambda n: bar.advance(task, n)

        options: dict = {"lmpc": {"bundle_dir": lmpc_bundles}} if lmpc_bundles is not None else {}
        if torque_rate_limit != "none":  # default left out: results.json's controller_options as before
            options.setdefault("lmpc", {})["torque_rate_limit"] = torque_rate_limit
        if velocity_filter_hz is not None:
            options.setdefault("lmpc", {})["velocity_filter_hz"] = velocity_filter_hz
        hmpc_options: dict = {}
        from models.hmpc.config import formulation_options

        hmpc_options.update(formulation_options(hmpc_formulation, arm.name))
        if hmpc_formulation == "anchored":
            hmpc_options["anchor_weight_scale"] = hmpc_anchor_scale
        if hmpc_prediction_step_s is not None:
            hmpc_options["prediction_step_s"] = hmpc_prediction_step_s
        if hmpc_options:
            options["hmpc"] = hmpc_options
        if hil is not None:  # --plant hil: models/hil_experiment/
            from models.hil_experiment import format_hil_table, run_hil_experiment

            results = run_hil_experiment(arm, condition_list, config, out, hil, progress=progress)
        else:
            results = run_experiment(arm, condition_list, config, out, controller_options=options, progress=progress)
    from models.experiment import format_table

    print(format_hil_table(results) if hil is not None else format_table(results))
    written = (
        ["results.json", "table.md"] + ([] if no_trajectories else ["trajectories/"]) + ([] if no_plots else ["plots/"])
    )
    if hil is not None and hil.parity:
        written.append("sim/")  # the simulation twin's own outputs
    console.print(f"wrote {out}/{', '.join(written)}", soft_wrap=True, highlight=False)  # one line, even piped
