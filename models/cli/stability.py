"""``hil stability``: Theorem 1's conditions for a law along an operating condition's reference.

The law is evaluated at the equilibrium e = 0 along the condition's reference (local stability is
about that equilibrium), its state rolled along it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from models.cli.options import RobotOption
from models.errors import ModelInputError


def stability(
    law: Annotated[str, typer.Argument(help="Feedback law: pd, pid, adrc, hinf, smc, mrac.")],
    conditions: Annotated[Path | None, typer.Option(help="Conditions YAML (default: the paper's five).")] = None,
    condition: Annotated[int, typer.Option(help="1-based index of the condition in the file.")] = 1,
    robot: RobotOption = "ur5_paper",
    period_s: Annotated[float, typer.Option(help="Control period (s); also the sampling of the reference.")] = 1e-3,
    beta: Annotated[float, typer.Option(help="Lyapunov cross-term weight beta.")] = 1e-6,
    epsilon: Annotated[float, typer.Option(help="Margin epsilon of Eqs. 19-20.")] = 1e-3,
    stride: Annotated[int, typer.Option(help="Evaluate every stride-th control period.")] = 10,
    gains: Annotated[str, typer.Option(help="Gain set: 'stabilized' (default) or 'paper'.")] = "stabilized",
    delay_periods: Annotated[
        int, typer.Option(help="Measurement delay of the delay-margin check, periods (0: skip the check).")
    ] = 1,
    poses: Annotated[int, typer.Option(help="Envelope poses of the linear delay-margin check.")] = 400,
    as_json: Annotated[bool, typer.Option("--json", help="Print the report as JSON.")] = False,
) -> None:
    """Evaluate Theorem 1 (Eqs. 19-21) with P = diag(25, 150, 65, 25, 2, 1); print margins (> 0 holds).

    Then the delay margin (docs/feedback_laws.md): PD, PID, ADRC, H-infinity by the spectral radius of
    the delayed discrete loop over seeded envelope poses; SMC and MRAC by simulating the condition
    with the delay."""
    from models.conditions import load_conditions
    from models.feedback import make_law
    from models.robots import load_robot
    from models.stability import evaluate_theorem1, roll_states

    if stride < 1:
        raise ModelInputError(f"--stride: must be >= 1, got {stride}")
    if delay_periods < 0 or poses < 1:
        raise ModelInputError(f"--delay-periods must be >= 0 and --poses >= 1, got {delay_periods} and {poses}")
    arm = load_robot(robot)
    condition_list = load_conditions(conditions, robot=arm)
    if not 1 <= condition <= len(condition_list):
        raise ModelInputError(f"--condition: {condition} is outside 1..{len(condition_list)}")
    chosen = condition_list[condition - 1]
    feedback = make_law(law, arm, period_s=period_s, gain_set=gains)
    t = np.arange(int(round(chosen.duration_s / period_s))) * period_s
    q_d, qd_d, qdd_d = chosen.reference(t)
    states = roll_states(feedback, q_d, qd_d, q_d, qd_d, qdd_d)[::stride]
    pick = slice(None, None, stride)
    report = evaluate_theorem1(
        feedback, arm, q_d[pick], qd_d[pick], q_d[pick], qd_d[pick], qdd_d[pick], states, beta=beta, epsilon=epsilon
    )
    delay = _delay_check(law, arm, chosen, gains, period_s, delay_periods, poses) if delay_periods else None
    if as_json:
        typer.echo(json.dumps({"condition": chosen.name, **report.as_dict(), "delay_margin": delay}, indent=2))
        return
    typer.echo(
        f"Theorem 1 for {law} on condition '{chosen.name}' ({report.samples} samples, beta={beta}, eps={epsilon})"
    )
    for key, margin in report.margins.items():
        typer.echo(f"  {key}: margin {margin:+.6g}  {'holds' if report.holds[key] else 'FAILS'}")
    for note in report.notes:
        typer.echo(f"  note: {note}")
    if delay is not None:
        typer.echo(_delay_line(delay))


def _delay_check(
    law: str, arm: Any, condition: Any, gains: str, period_s: float, delay_periods: int, poses: int
) -> dict[str, Any]:
    from models.delay_margin import LINEAR_LAWS, delay_margin, simulated_delay_check
    from models.feedback import make_law

    if law in LINEAR_LAWS:
        feedback = make_law(law, arm, period_s=period_s, gain_set=gains)
        return delay_margin(feedback, arm, delay_periods, count=poses).as_dict()
    return simulated_delay_check(law, arm, [condition], gains, delay_periods, period_s)


def _delay_line(delay: dict[str, Any]) -> str:
    verdict = "holds" if delay["holds"] else "FAILS"
    if delay["method"] == "simulation":
        return (
            f"Delay margin ({delay['delay_periods']} period(s), by simulation of the condition): {verdict}; "
            f"max |qd| / limit {max(delay['velocity_limit_ratio']):.3g}"
        )
    return (
        f"Delay margin ({delay['delay_periods']} period(s), linear, {delay['poses']} envelope poses): {verdict}; "
        f"unstable poses {delay['unstable_poses']} ({delay['delay_induced_unstable_poses']} by the delay, "
        f"{delay['unstable_poses_without_delay']} without it); worst spectral radius "
        f"{delay['worst_spectral_radius']:.6f} (growth {delay['worst_growth_rate_per_s']:+.3g}/s), without the "
        f"delay {delay['worst_spectral_radius_without_delay']:.6f}"
    )
