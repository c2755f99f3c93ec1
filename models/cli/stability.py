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

from models.cli.options import GainsOption, RobotOption, gain_set_for
from models.errors import ModelInputError


def stability(
    law: Annotated[str, typer.Argument(help="Feedback law: pd, pid, adrc, hinf, smc, mrac.")],
    conditions: Annotated[Path | None, typer.Option(help="Conditions YAML (default: the paper's five).")] = None,
    condition: Annotated[
        int, typer.Option(help="1-based index of the condition in the file; 0: every condition (the envelope).")
    ] = 1,
    robot: RobotOption = "ur5_paper",
    period_s: Annotated[float, typer.Option(help="Control period (s); also the sampling of the reference.")] = 1e-3,
    beta: Annotated[float, typer.Option(help="Lyapunov cross-term weight beta.")] = 1e-6,
    epsilon: Annotated[float, typer.Option(help="Margin epsilon of Eqs. 19-20.")] = 1e-3,
    stride: Annotated[int, typer.Option(help="Evaluate every stride-th control period.")] = 10,
    gains: GainsOption = None,
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
    gains = gain_set_for(arm.name, gains)
    condition_list = load_conditions(conditions, robot=arm)
    if not 0 <= condition <= len(condition_list):
        raise ModelInputError(f"--condition: {condition} is outside 0..{len(condition_list)} (0: all)")
    chosen_list = condition_list if condition == 0 else [condition_list[condition - 1]]
    feedback = make_law(law, arm, period_s=period_s, gain_set=gains)
    p_matrix = _lyapunov_p(arm, gains, period_s)
    reports = []
    for chosen in chosen_list:
        t = np.arange(int(round(chosen.duration_s / period_s))) * period_s
        q_d, qd_d, qdd_d = chosen.reference(t)
        states = roll_states(feedback, q_d, qd_d, q_d, qd_d, qdd_d)[::stride]
        pick = slice(None, None, stride)
        signals = (q_d[pick], qd_d[pick], q_d[pick], qd_d[pick], qdd_d[pick])
        reports.append(
            (chosen, evaluate_theorem1(feedback, arm, *signals, states, p_matrix, beta=beta, epsilon=epsilon))
        )
    delay = _delay_check(law, arm, chosen_list, gains, period_s, delay_periods, poses) if delay_periods else None
    if as_json:
        payload = [{"condition": c.name, **r.as_dict()} for c, r in reports]
        typer.echo(
            json.dumps(
                {**payload[0], "delay_margin": delay}
                if condition
                else {"robot": arm.name, "gains": gains, "conditions": payload, "delay_margin": delay},
                indent=2,
            )
        )
        return
    for chosen, report in reports:
        typer.echo(
            f"Theorem 1 for {law} ({arm.name}, gains '{gains}') on condition '{chosen.name}' ({report.samples} "
            f"samples, beta={beta}, eps={epsilon})"
        )
        for key, margin in report.margins.items():
            typer.echo(f"  {key}: margin {margin:+.6g}  {'holds' if report.holds[key] else 'FAILS'}")
        for note in report.notes:
            typer.echo(f"  note: {note}")
    if delay is not None:
        typer.echo(_delay_line(delay))


def _lyapunov_p(arm: Any, gains: str, period_s: float) -> np.ndarray:
    """The paper's P = diag(its PD Kp) on its arm; with designed gains, the designed PD's Kp (same reading)."""
    from models.feedback import DESIGNED_GAIN_SET
    from models.stability import PAPER_P

    if gains != DESIGNED_GAIN_SET and arm.n_joints == PAPER_P.shape[0]:
        return PAPER_P
    from models.feedback.design import design_law

    return np.diag(np.asarray(design_law(arm, "pd", period_s)["kp"], float))


def _delay_check(
    law: str, arm: Any, conditions: list[Any], gains: str, period_s: float, delay_periods: int, poses: int
) -> dict[str, Any]:
    from models.delay_margin import LINEAR_LAWS, delay_margin, simulated_delay_check
    from models.feedback import make_law

    if law in LINEAR_LAWS:
        feedback = make_law(law, arm, period_s=period_s, gain_set=gains)
        return delay_margin(feedback, arm, delay_periods, count=poses).as_dict()
    return simulated_delay_check(law, arm, conditions, gains, delay_periods, period_s)


def _delay_line(delay: dict[str, Any]) -> str:
    verdict = "holds" if delay["holds"] else "FAILS"
    if delay["method"] == "simulation":
        return (
            f"Delay margin ({delay['delay_periods']} period(s), by simulation of {', '.join(delay['conditions'])}): "
            f"{verdict}; "
            f"max |qd| / limit {max(delay['velocity_limit_ratio']):.3g}"
        )
    return (
        f"Delay margin ({delay['delay_periods']} period(s), linear, {delay['poses']} envelope poses): {verdict}; "
        f"unstable poses {delay['unstable_poses']} ({delay['delay_induced_unstable_poses']} by the delay, "
        f"{delay['unstable_poses_without_delay']} without it); worst spectral radius "
        f"{delay['worst_spectral_radius']:.6f} (growth {delay['worst_growth_rate_per_s']:+.3g}/s), without the "
        f"delay {delay['worst_spectral_radius_without_delay']:.6f}"
    )
