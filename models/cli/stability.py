"""``hil stability``: Theorem 1's conditions for a law along an operating condition's reference.

The law is evaluated at the equilibrium e = 0 along the condition's reference (local stability is
about that equilibrium), its state rolled along it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

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
    as_json: Annotated[bool, typer.Option("--json", help="Print the report as JSON.")] = False,
) -> None:
    """Evaluate Theorem 1 (Eqs. 19-21) with P = diag(25, 150, 65, 25, 2, 1); print margins (> 0 holds)."""
    from models.conditions import load_conditions
    from models.feedback import make_law
    from models.robots import load_robot
    from models.stability import evaluate_theorem1, roll_states

    if stride < 1:
        raise ModelInputError(f"--stride: must be >= 1, got {stride}")
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
    if as_json:
        typer.echo(json.dumps({"condition": chosen.name, **report.as_dict()}, indent=2))
        return
    typer.echo(
        f"Theorem 1 for {law} on condition '{chosen.name}' ({report.samples} samples, beta={beta}, eps={epsilon})"
    )
    for key, margin in report.margins.items():
        typer.echo(f"  {key}: margin {margin:+.6g}  {'holds' if report.holds[key] else 'FAILS'}")
    for note in report.notes:
        typer.echo(f"  note: {note}")
