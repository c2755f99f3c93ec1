"""``hil config``: configs made for the user instead of written by hand (docs/any_arm.md).

hil config runtime --bundle models/bundles/panda/pd --bus bus.yaml --out runtime.yaml
hil config conditions --robot panda --out panda_conditions.yaml
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer

from models.cli.options import RobotOption, one_of

config_app = typer.Typer(help="Write a runtime config from a bundle and a drive table; a robot's conditions.")


@config_app.command("runtime")
def runtime(
    bundle: Annotated[Path, typer.Option(help="The policy bundle directory (manifest.json, policy.onnx).")],
    bus: Annotated[
        Path,
        typer.Option(help="The drive table (YAML): transport, bus fields, drives: {joint: node id} (docs/any_arm.md)."),
    ],
    out: Annotated[Path, typer.Option(help="The runtime config to write (hil run --config FILE).")] = Path(
        "runtime.yaml"
    ),
    mode: Annotated[str, typer.Option(help="lmpc: law + emulator; fb: the bundle's law alone.")] = "lmpc",
    condition: Annotated[
        str | None, typer.Option(help="The condition run after a ramp from the measured pose; 'hold': hold the pose.")
    ] = "C1",
    conditions: Annotated[
        Path | None,
        typer.Option(help="Conditions YAML (default: the robot's five; ur5_paper: the paper's, written beside --out)."),
    ] = None,
    robot: Annotated[
        str | None, typer.Option(help="The bundle's robot as a URDF path, when it is not built in (its conditions).")
    ] = None,
    encoder_noise_rad: Annotated[
        float | None,
        typer.Option(
            help="The encoders' position noise, RMS (jitter and quantization; default: the runtime's, about one "
            "increment of a 19-bit encoder). An lmpc bundle that turns it into torque steps beyond the robot's rate "
            "bound is refused."
        ),
    ] = None,
    velocity_noise_rad_s: Annotated[
        float | None,
        typer.Option(help="The drives' velocity noise, RMS (default: the position differenced over one period)."),
    ] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite --out.")] = False,
) -> None:
    """A runtime config from a bundle and a drive table, checked as ``hil run`` checks it."""
    from hil_runtime.bundle import DEFAULT_ENCODER_NOISE_RAD
    from models.errors import ModelInputError
    from models.lab.deploy import runtime_config_from_bundle

    one_of(mode, ("lmpc", "fb"), "--mode")
    for flag, value in (("--encoder-noise-rad", encoder_noise_rad), ("--velocity-noise-rad-s", velocity_noise_rad_s)):
        if value is not None and not (math.isfinite(value) and value >= 0.0):
            raise ModelInputError(f"{flag}: must be a finite RMS noise >= 0, got {value!r}")
    if out.exists() and not force:
        raise ModelInputError(f"--out: {out} exists (--force to overwrite)")
    data = runtime_config_from_bundle(
        bundle,
        bus,
        out,
        mode,
        None if condition == "hold" else condition,
        conditions,
        robot,
        (DEFAULT_ENCODER_NOISE_RAD if encoder_noise_rad is None else encoder_noise_rad, velocity_noise_rad_s),
    )
    joints = ", ".join(f"{j['name']}@{j['node_id']}" for j in data["bus"]["joints"])
    print(f"wrote {out} (robot {data['robot']}, {len(data['bus']['joints'])} joints: {joints})")


@config_app.command("conditions")
def conditions(
    robot: RobotOption = "ur5_paper",
    out: Annotated[Path, typer.Option(help="The conditions file to write.")] = Path("conditions.yaml"),
) -> None:
    """The robot's five default conditions (the paper's for ur5_paper) as a conditions file."""
    from models.conditions import load_conditions
    from models.hil_experiment.config import conditions_yaml
    from models.robots import load_robot

    arm = load_robot(robot)
    items = load_conditions(None, robot=arm)
    out.write_text(f"# the default conditions of {arm.name} (models/default_conditions.py)\n" + conditions_yaml(items))
    print(f"wrote {out} ({', '.join(c.name for c in items)} for {arm.name}, {arm.n_joints} joints)")


__all__ = ["config_app"]
