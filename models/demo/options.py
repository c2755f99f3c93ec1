"""What ``hil demo`` is asked to run: the options, checked before any process starts, and the
paper's condition they select."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from models.errors import ModelInputError

#: The best LMPC law of Table I (README, docs/lmpc.md): the lowest LMPC composite score (lower is
#: better), MRAC 0.025 beside 0.027-0.031 for the other laws' structured bundles. Check it again
#: when the bundles are re-exported.
BEST_LMPC_LAW = "mrac"
DEFAULT_CONDITION = "C1"
MODES = ("lmpc", "fb")


@dataclass(frozen=True)
class DemoOptions:
    law: str = BEST_LMPC_LAW
    mode: str = "lmpc"  # lmpc: the fused law + emulator bundle; fb: the bundle's law alone
    condition: str = DEFAULT_CONDITION
    duration_s: float | None = None  # None: the condition's own (5 s for the paper's)
    realtime: bool = False  # free-running: the target on its own clock, the runtime on absolute deadlines
    target_substeps: int | None = None  # pybullet steps per control period; None: the target's per clock
    cpus: str = "auto"  # --realtime: auto, none or RUNTIME,TARGET (sim_target.rt_settings.split_cpus)
    robot: str = "ur5_paper"
    realism: str = "ideal"  # a realism profile or profile file, applied by the target and the twin (docs/realism.md)


def check_options(options: DemoOptions) -> None:
    """Refuse bad input with one line (exit 2) before any process starts."""
    from models.feedback import LAW_NAMES

    if not sys.platform.startswith("linux"):
        raise ModelInputError("hil demo: the ipc bus between the processes is Linux only (docs/ipc_bus.md)")
    if options.law not in LAW_NAMES:
        raise ModelInputError(f"--law: unknown '{options.law}' (known: {', '.join(LAW_NAMES)})")
    if options.mode not in MODES:
        raise ModelInputError(f"--mode: unknown '{options.mode}' (known: {', '.join(MODES)})")
    manifest = bundle_dir(options) / "manifest.json"
    if not manifest.is_file():
        raise ModelInputError(f"{manifest}: no bundle for law '{options.law}' (export one with `hil pipeline`)")
    if options.duration_s is not None and not (math.isfinite(options.duration_s) and options.duration_s >= 0.05):
        raise ModelInputError(f"--duration: must be a finite number of seconds >= 0.05, got {options.duration_s!r}")
    if options.target_substeps is not None and options.target_substeps < 1:
        raise ModelInputError(f"--target-substeps: must be >= 1, got {options.target_substeps}")
    from sim_target.rt_settings import split_cpus

    try:
        split_cpus(options.cpus)
    except ValueError as exc:
        raise ModelInputError(str(exc)) from None
    target, _ = realism_specs(options)  # a bad profile: one line naming the file and field
    if options.mode == "lmpc":  # what the daemon would refuse at load, refused before anything starts
        from hil_runtime.bundle import BundleError, PolicyBundle

        try:
            PolicyBundle.load(bundle_dir(options)).check_sensing(*target.measurement_noise())
        except BundleError as exc:
            raise ModelInputError(
                f"--realism {options.realism}: {exc} (the runtime refuses it on an arm with this sensing: "
                "docs/runtime.md, bundle.encoder_noise_rad)"
            ) from None


def bundle_dir(options: DemoOptions) -> Path:
    """The shipped bundle of the robot's law: models/bundles/<robot name>/<law>/ (a bad robot: one line)."""
    from models.lmpc.controller import bundle_path
    from models.robots import load_robot

    return bundle_path(load_robot(options.robot).name, options.law, None)


def target_substeps(options: DemoOptions) -> int:
    """The target's pybullet steps per period: the option's, else its clock's default (sim_target/config.py)."""
    from sim_target.config import LOCKSTEP_SUBSTEPS, REALTIME_SUBSTEPS

    if options.target_substeps is not None:
        return options.target_substeps
    return REALTIME_SUBSTEPS if options.realtime else LOCKSTEP_SUBSTEPS


def realism_specs(options: DemoOptions) -> tuple[Any, Any]:
    """The profile bound to the target's physics step and to the simulation twin's, both checked."""
    from models.robots import load_robot
    from models.sim import SimConfig
    from sim_target.realism_profiles import load_realism

    robot = load_robot(options.robot)
    sim = SimConfig()
    n, limit = robot.n_joints, robot.torque_limit_nm
    target = load_realism(options.realism, n, sim.period_s, sim.period_s / target_substeps(options), limit)
    twin = load_realism(options.realism, n, sim.period_s, sim.period_s / sim.substeps, limit)
    return target, twin


def demo_condition(options: DemoOptions, robot: Any) -> Any:
    """The robot's default condition (the paper's for ur5_paper), cut to ``duration_s`` when given
    (its disturbance kept where it falls)."""
    from models.conditions import load_conditions

    conditions = load_conditions(None, robot=robot)
    for condition in conditions:
        if condition.name == options.condition:
            if options.duration_s is not None:
                condition = replace(condition, duration_s=float(options.duration_s))
                d = condition.disturbance
                if d is not None and d.time_s >= condition.duration_s:
                    condition = replace(condition, disturbance=None)  # the run ends before it
            return condition
    names = ", ".join(c.name for c in conditions)
    raise ModelInputError(f"--condition: unknown '{options.condition}' (the robot's: {names})")


__all__ = ["BEST_LMPC_LAW", "DEFAULT_CONDITION", "MODES", "DemoOptions", "check_options", "demo_condition"]
