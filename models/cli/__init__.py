"""The ``hil`` commands of the science side, one module per command:

    experiment.py   hil experiment   laws x modes x conditions, simulated or HIL (Table I, Table II)
    pipeline.py     hil pipeline     the LMPC bundles from scratch (models/lmpc/pipeline/, structured)
    demo.py         hil demo         the runtime on the emulated arm, watched live (models/demo/)
    stability.py    hil stability    Theorem 1's conditions along a reference
    (lab)           hil faults       the fault campaign (models/lab/faults/cli.py, docs/faults.md)
    config.py       hil config       a runtime config from a bundle and a drive table; a robot's conditions
    options.py      the value checks they share (one line naming the option, exit code 2)

``register`` adds them to the ``hil`` root; hil_runtime/cli.py finds it through the ``hil.commands``
entry point (pyproject.toml), so the runtime never imports ``models``. Each command imports its heavy
dependencies (torch, pinocchio, pybullet) inside its function, so ``hil --help`` stays quick.
"""

from __future__ import annotations

import typer

from models.cli.experiment import experiment
from models.cli.options import ROBOTS_HELP


def register(app: typer.Typer) -> None:
    """Add the science commands to the ``hil`` root (an entry point in pyproject.toml)."""
    from models.cli.config import config_app
    from models.cli.demo import demo
    from models.cli.pipeline import pipeline
    from models.cli.stability import stability
    from models.lab.faults.cli import faults

    app.command("experiment")(experiment)
    app.command("pipeline")(pipeline)
    app.command("demo")(demo)
    app.command("stability")(stability)
    app.command("faults")(faults)
    app.add_typer(config_app, name="config")


__all__ = ["ROBOTS_HELP", "experiment", "register"]
