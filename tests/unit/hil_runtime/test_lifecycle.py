"""Lifecycle transitions (ros2_control's): the table, refusals, fault reasons, listeners."""

from __future__ import annotations

import itertools

import pytest

from hil_runtime.lifecycle import (
    TRANSITIONS,
    Lifecycle,
    LifecycleError,
    LifecycleState,
    Transition,
)

S, T = LifecycleState, Transition


def _at(state: LifecycleState) -> Lifecycle:
    life = Lifecycle()
    path = {
        S.UNCONFIGURED: [],
        S.INACTIVE: [T.CONFIGURE],
        S.ACTIVE: [T.CONFIGURE, T.ACTIVATE],
        S.FAULT: [T.CONFIGURE, T.ACTIVATE, T.FAULT],
        S.FINALIZED: [T.SHUTDOWN],
    }[state]
    for transition in path:
        life.apply(transition, "x")
    assert life.state is state
    return life


@pytest.mark.parametrize(("state", "transition"), list(itertools.product(LifecycleState, Transition)))
def test_every_pair_is_allowed_exactly_when_the_table_says(state: LifecycleState, transition: Transition) -> None:
    life = _at(state)
    target = TRANSITIONS.get((state, transition))
    if target is None:
        with pytest.raises(LifecycleError, match=f"cannot {transition.value} from {state.value}"):
            life.apply(transition)
        assert life.state is state
    else:
        assert life.apply(transition, "why") is target


def test_the_normal_path_and_the_fault_path() -> None:
    seen: list[tuple[LifecycleState, str | None]] = []
    life = Lifecycle()
    life.subscribe(lambda state, fault: seen.append((state, fault)))
    for transition in (T.CONFIGURE, T.ACTIVATE, T.FAULT, T.RESET, T.ACTIVATE, T.SHUTDOWN):
        life.apply(transition, "heartbeat_lost: drive 3" if transition is T.FAULT else None)
    assert seen == [
        (S.INACTIVE, None),
        (S.ACTIVE, None),
        (S.FAULT, "heartbeat_lost: drive 3"),
        (S.INACTIVE, None),
        (S.ACTIVE, None),
        (S.FINALIZED, None),
    ]


def test_finalized_is_terminal_and_faults_keep_the_latest_reason() -> None:
    assert not any(state is S.FINALIZED for (state, _t) in TRANSITIONS)
    life = _at(S.FAULT)
    life.apply(T.FAULT, "second")
    assert life.fault == "second"
    assert not life.can(T.ACTIVATE)  # only a reset leaves FAULT (or shutdown)
