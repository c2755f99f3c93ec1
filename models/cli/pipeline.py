"""``hil pipeline``: recreate the LMPC policy bundles from scratch (dataset, labels, training, export)."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Annotated, Any

import typer

from models.cli.options import GainsOption, RobotOption, gain_set_for, one_of, split_names
from models.errors import ModelInputError

STAGES = ("dataset", "label", "train", "augment", "export")


def pipeline(
    stages: Annotated[
        str, typer.Option(help="Comma-separated stages: dataset, label, train, augment (beyond the paper), export.")
    ] = ",".join(STAGES),
    work: Annotated[
        Path,
        typer.Option(
            help="Working directory (raw.h5, labels.h5, training, plots); results/lmpc/<robot> for another arm."
        ),
    ] = Path("results/lmpc"),
    bundles: Annotated[Path, typer.Option(help="Where bundles go: <bundles>/<robot>/<law>/.")] = Path("models/bundles"),
    laws: Annotated[str, typer.Option(help="Comma-separated feedback laws.")] = "pd,pid,adrc,hinf,smc,mrac",
    robot: RobotOption = "ur5_paper",
    gains: GainsOption = None,
    conditions: Annotated[int, typer.Option(help="Random operating conditions in D_input.")] = 100,
    seed: Annotated[int, typer.Option(help="Seed of the random conditions.")] = 20240601,
    budget: Annotated[int, typer.Option(help="Labeled samples over all laws (Theorem 2 budget).")] = 100_000,
    duration: Annotated[float, typer.Option(help="Run length (s).")] = 5.0,
    epochs: Annotated[int, typer.Option(help="Max training epochs.")] = 150,
    workers: Annotated[int | None, typer.Option(help="Workers (default: one per CPU; 1: serial).")] = None,
    executor: Annotated[
        str,
        typer.Option(
            help="Where the workers run (simulation, HMPC labeling, training): 'local' processes, 'serial' (this "
            "process) or 'ray' (a local Ray on 127.0.0.1; the ray extra)."
        ),
    ] = "local",
    lipschitz: Annotated[str, typer.Option(help="L*Delta_i: 'zero' (paper's reading) or 'estimate'.")] = "zero",
    rollouts: Annotated[
        int, typer.Option(help="Pool conditions run under the HMPC for the augment stage (0: paper's recipe only).")
    ] = 60,
    dagger_rounds: Annotated[int, typer.Option(help="DAgger rounds in the augment stage.")] = 0,
    force_dataset: Annotated[bool, typer.Option("--force-dataset", help="Regenerate raw.h5 even if present.")] = False,
    design: Annotated[
        str,
        typer.Option(
            help="'structured' (nominal feed-forward in the graph + bounded residual; docs/lmpc.md section 9; "
            "its own stages: rollouts, relabel, fit, export; the default) or 'paper' (Eq. 22 MLP, Theorem 2; the "
            "stages above)."
        ),
    ] = "structured",
    hmpc_formulation: Annotated[
        str, typer.Option(help="The HMPC imitated: 'absolute', 'anchored' or 'deployable' (docs/hmpc.md).")
    ] = "deployable",
    target: Annotated[
        str, typer.Option(help="Structured design: 'hmpc', or 'law' (the control row: imitate the law itself).")
    ] = "hmpc",
    ff_point: Annotated[
        str, typer.Option(help="Structured design: feed-forward at the 'measured' state or along the 'reference'.")
    ] = "measured",
    train_conditions: Annotated[int, typer.Option(help="Structured design: paper-range training conditions.")] = 16,
    residual_bound_scale: Annotated[
        float,
        typer.Option(
            help="Structured design: trust-region residual bound, x the largest |tau* - tau_fb| of the labels."
        ),
    ] = 10.0,
    tau_prev: Annotated[
        bool,
        typer.Option(
            "--tau-prev/--no-tau-prev",
            help="Structured design: the emulator also reads the last commanded torque and steps from it within "
            "the rate bound (docs/lmpc.md section 11).",
        ),
    ] = False,
    beta_floor: Annotated[
        float, typer.Option(help="Structured design, --tau-prev: the smallest step share beta per joint (0-1].")
    ] = 0.3,
    rate_check: Annotated[
        bool,
        typer.Option(
            "--rate-check/--no-rate-check",
            help="Structured design, --tau-prev: slow the static gains until the exported bundle's bounded loop "
            "holds the most training conditions (docs/lmpc.md section 11, 'The rate check').",
        ),
    ] = False,
    physics_fit: Annotated[
        str,
        typer.Option(
            help="Structured design: the physics part's fit, 'free' (every shipped bundle), 'stable' (g = 1, "
            "the loop e'' = -(K_p e + K_d e') stable by construction; docs/any_arm.md \"The stable physics fit\") "
            "or 'bounded' (g >= 0.5 per joint, K_p, K_d on the stable fit's floors; docs/lmpc.md section 12)."
        ),
    ] = "free",
    law_coefficient: Annotated[
        str,
        typer.Option(
            help="Structured design: the law's coefficient c (tau_L = (1 + c) tau_fb + ...): 'fixed' (the "
            "formulation's: -1, the law cancelled, for 'absolute' and 'deployable') or 'fitted' (c in [-1.05, 0] "
            "per joint; docs/lmpc.md section 10, 'Does the law matter')."
        ),
    ] = "fixed",
    train_realism: Annotated[
        str | None,
        typer.Option(
            help="Structured design: run the expert's training rollouts in seeded worlds drawn around this realism "
            "profile (name or YAML; domain randomization, docs/lmpc.md section 12). Default: the ideal world."
        ),
    ] = None,
    realism_draws: Annotated[
        int, typer.Option(help="Structured design, --train-realism: randomized worlds (training conditions rotate).")
    ] = 4,
    ideal_draws: Annotated[
        int,
        typer.Option(
            help="Structured design, --train-realism: more training worlds that are the ideal one (the nominal "
            "plant among the randomized draws)."
        ),
    ] = 0,
    envelope_conditions: Annotated[
        int,
        typer.Option(
            help="Structured design: training conditions across the arm's envelope beside the paper-range ones "
            "(models/envelope_conditions.py; the trust box then covers them)."
        ),
    ] = 0,
) -> None:
    """Dataset -> Theorem 2 sampling -> HMPC labels -> emulators -> policy bundles, with progress bars."""
    from models.executors import EXECUTORS
    from models.feedback import LAW_NAMES

    one_of(executor, EXECUTORS, "--executor")
    if workers is not None and workers < 1:
        raise ModelInputError(f"--workers: must be >= 1, got {workers}")
    one_of(design, ("paper", "structured"), "--design")
    from models.hmpc.config import FORMULATIONS

    one_of(hmpc_formulation, tuple(FORMULATIONS), "--hmpc-formulation")
    law_list = split_names(laws, LAW_NAMES, "laws")
    stage_list = split_names(stages, STAGES, "stages")
    if design == "structured" and stage_list != STAGES:
        raise ModelInputError(
            "--stages: the stages of --design paper (the structured design, the default, runs rollouts, relabel, "
            "fit and export)"
        )
    from models.robot_target import robot_spec
    from models.robots import load_robot

    arm = load_robot(robot)  # a bad name or URDF: one line before any work
    robot, gain_set = robot_spec(arm), gain_set_for(arm.name, gains)
    if arm.name != "ur5_paper" and work == Path("results/lmpc"):  # the default: one directory per robot
        work = work / arm.name
    if design == "structured":
        if not residual_bound_scale > 0:
            raise ModelInputError(f"--residual-bound-scale: must be > 0, got {residual_bound_scale}")
        if not 0.0 < beta_floor <= 1.0:
            raise ModelInputError(f"--beta-floor: must be in (0, 1], got {beta_floor}")
        from models.lmpc.structured.config import PHYSICS_FITS

        one_of(physics_fit, PHYSICS_FITS, "--physics-fit")
        one_of(law_coefficient, ("fixed", "fitted"), "--law-coefficient")
        if realism_draws < 1:
            raise ModelInputError(f"--realism-draws: must be >= 1, got {realism_draws}")
        if envelope_conditions < 0:
            raise ModelInputError(f"--envelope-conditions: must be >= 0, got {envelope_conditions}")
        if ideal_draws < 0:
            raise ModelInputError(f"--ideal-draws: must be >= 0, got {ideal_draws}")
        if train_realism is not None:  # a bad profile: one line before any work
            from sim_target.realism import RealismError
            from sim_target.realism_profiles import load_realism

            try:
                load_realism(train_realism, arm.n_joints, 1e-3, 5e-4, arm.torque_limit_nm)
            except RealismError as exc:  # the profile reader names --realism: this option is another
                raise ModelInputError(str(exc).replace("--realism:", "--train-realism:", 1)) from None
        _structured(
            work,
            bundles,
            law_list,
            hmpc_formulation,
            target,
            ff_point,
            train_conditions,
            dagger_rounds,
            residual_bound_scale,
            executor,
            workers,
            robot,
            gain_set,
            tau_prev,
            beta_floor,
            physics_fit,
            rate_check,
            law_coefficient == "fitted",
            {
                "train_realism": train_realism,
                "realism_draws": realism_draws,
                "ideal_draws": ideal_draws,
                "envelope_conditions": envelope_conditions,
            },
        )
        return
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from models.lmpc.pipeline import PipelineConfig, run_pipeline

    one_of(lipschitz, ("zero", "estimate"), "--lipschitz")
    if conditions < 2:
        raise ModelInputError(f"--conditions: need >= 2 (a pool and held-out ones), got {conditions}")
    base = PipelineConfig()
    config = replace(
        base,
        dataset=replace(
            base.dataset,
            robot=robot,
            gain_set=gain_set,
            laws=law_list,
            conditions=conditions,
            seed=seed,
            duration_s=duration,
        ),
        budget=budget,
        pool_conditions=max(1, int(round(0.9 * conditions))),
        test_per_law=min(base.test_per_law, max(10, budget // (5 * len(law_list)))),
        train=replace(base.train, max_epochs=epochs),
        workers=workers,
        executor=executor,
        rollout_conditions=rollouts,
        dagger_rounds=dagger_rounds,
        dagger_conditions=min(base.dagger_conditions, max(1, int(round(0.9 * conditions)))),
        lipschitz_delta="estimate" if lipschitz == "estimate" else (0.0, 0.0, 0.0),
    )
    console = Console(stderr=True)
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=console) as bar:

        def progress(label: str, total: int) -> Callable[[int], None]:
            task = bar.add_task(label, total=total)
            return lambda n: bar.advance(task, n)

        summary = run_pipeline(config, work, bundles, stage_list, progress=progress, force_dataset=force_dataset)
    console.print(f"[bold]wall time[/bold] (s): {json.dumps(summary['wall_s'])}")
    training = summary.get("training")
    if training:
        for law, row in training["per_law"].items():
            console.print(
                f"{law:5s} val MSE optimal {row['optimal']['val_mse_mean']:.4f} "
                f"uniform {row['uniform']['val_mse_mean']:.4f} | "
                f"test MSE optimal {row['optimal']['test_mse_mean']:.4f} uniform {row['uniform']['test_mse_mean']:.4f}"
            )
        console.print(f"mean optimal/uniform ratio: {json.dumps(training['mean_ratio_optimal_over_uniform'])}")
    for info in summary.get("bundles", {}).values():
        console.print(f"bundle {info['path']} (onnx vs torch {info['onnx_vs_torch_max_abs_nm']:.1e} N m)")
    console.print(f"wrote {work}/pipeline.json")


def _structured(
    work: Path,
    bundles: Path,
    law_list: tuple[str, ...],
    formulation: str,
    target: str,
    ff_point: str,
    conditions: int,
    dagger_rounds: int,
    bound_scale: float = 10.0,
    executor: str = "local",
    workers: int | None = None,
    robot: str = "ur5_paper",
    gain_set: str = "stabilized",
    tau_prev: bool = False,
    beta_floor: float = 0.3,
    physics_fit: str = "free",
    rate_check: bool = False,
    fit_law_coefficient: bool = False,
    training_world: dict[str, Any] | None = None,
) -> None:
    """``hil pipeline --design structured``: models.lmpc.structured.run_structured, one line per step."""
    import torch
    from rich.console import Console

    from models.executors import make_executor
    from models.lmpc.structured import C_FIXED, PERTURBATION, StructuredConfig, run_structured

    torch.set_num_threads(1)
    from models.hmpc.config import formulation_options
    from models.robots import load_robot

    robot_name = load_robot(robot).name
    options = formulation_options(formulation, robot_name)
    sigma_e, sigma_rate = PERTURBATION[formulation]
    config = StructuredConfig(
        robot=robot,
        gain_set=gain_set,
        laws=law_list,
        hmpc_options=options,
        target=target,
        ff_point=ff_point,
        train_conditions=conditions,
        perturb_error_rad=sigma_e,
        perturb_rate_rad_s=sigma_rate,
        dagger_rounds=dagger_rounds,
        c_fixed=C_FIXED[formulation] if target == "hmpc" and not fit_law_coefficient else None,
        bound_scale=bound_scale,
        previous_torque=tau_prev,
        beta_floor=beta_floor,
        physics_fit=physics_fit,
        rate_check=rate_check,
        **(training_world or {}),  # train_realism, realism_draws, ideal_draws, envelope_conditions
    )
    console = Console(stderr=True)
    with make_executor(executor, workers) as pool:
        summary = run_structured(config, bundles, work, log=console.print, executor=pool)
    console.print(f"wrote {bundles}/<robot>/<law>/ and {work}/structured.json ({summary['wall_s']:.0f} s)")
