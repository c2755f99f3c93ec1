"""``hil faults [--quick] [--out DIR]``: the fault-injection campaign (docs/faults.md)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer


def faults(
    out: Annotated[Path, typer.Option("--out", help="output directory: results.json and table.md")] = Path(
        "results/faults"
    ),
    quick: Annotated[
        bool, typer.Option("--quick", help="the subset the test suite runs (about a minute), one repeat")
    ] = False,
    repeats: Annotated[int | None, typer.Option(help="runs of each fault (default 3; 1 with --quick)")] = None,
    seed: Annotated[int, typer.Option(help="base seed of the repeats")] = 0,
    only: Annotated[str | None, typer.Option(help="comma-separated fault names (see docs/faults.md)")] = None,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="the runtime's and target's logs too")] = False,
) -> None:
    """Inject every fault into a live runtime + pybullet target; exit 1 if any row fails."""
    import logging

    from hil_runtime.outputs import prepare_output_dir, remove_if_empty
    from models.lab.faults.campaign import run_campaign, select
    from models.lab.faults.cases import CaseResult

    names = tuple(x.strip() for x in only.split(",") if x.strip()) if only else None
    select(quick, names)  # unknown names: one line, exit 2, before any work
    # The runtime logs every FAULT it enters; here they are the expected outcome, in the table.
    logging.basicConfig(level=logging.INFO if verbose else logging.CRITICAL, format="%(asctime)s %(name)s %(message)s")
    out_dir = prepare_output_dir(out)
    count = repeats if repeats is not None else (1 if quick else 3)

    def progress(r: CaseResult) -> None:
        mark = "pass" if r.passed else "FAIL: " + "; ".join(r.failures)
        print(f"  {r.fault} #{r.repeat}: {r.action} [{mark}] ({r.wall_s} s)", file=sys.stderr, flush=True)

    try:
        document = run_campaign(out_dir, quick=quick, repeats=count, seed=seed, only=names, progress=progress)
    except BaseException:  # Ctrl-C or a failure: no empty directory left behind (outputs are atomic)
        remove_if_empty(out_dir)
        raise
    failed = [row["fault"] for row in document["rows"] if not row["pass"]]
    print(
        f"wrote {out_dir / 'table.md'} and {out_dir / 'results.json'}: {len(document['rows'])} faults, "
        + ("every row passes" if not failed else f"FAILED: {', '.join(failed)}")
    )
    if failed:
        raise typer.Exit(1)
