"""The campaign's realism cases (issue 23): the target applies a realism profile (docs/realism.md)
from activation, and the runtime must ride it or stop on a limit — a plant change, not a fault."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from models.lab.faults import cases as c

PROFILES = ("realistic", "harsh")


def case(profile: str) -> Any:
    """The case runner: the PD bundle's loop on a target built with ``realism: profile``."""

    def run(name: str, repeat: int, seed: int, work: Path) -> c.CaseResult:
        return c.run_in_process(
            name,
            repeat,
            seed,
            lambda rig, rng: None,
            c.Expect(may_fault=c.LIMIT_FAULTS, event=False, max_cycles=None),
            fault_at_activation=True,
            observe_cycles=1500,
            target_extra={"realism": profile},
        )

    return run


def faults(spec: type) -> tuple[Any, ...]:
    """The FaultSpec rows (``spec``: campaign.FaultSpec, passed in to keep the import one way)."""
    return tuple(
        spec(
            f"realism_{profile}",
            f"the {profile} world from activation (docs/realism.md)",
            "not a fault: tolerated, or a limit FAULT",
            False,
            case(profile),
        )
        for profile in PROFILES
    )
