"""check_law on every law (both gain sets, another joint count), and on laws that break each promise."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from models.feedback import GAIN_SETS, LAW_NAMES, make_law
from models.feedback.checks import LawCheckError, check_law
from models.feedback.pd import PDLaw
from models.feedback.pid import PIDLaw
from models.robots import load_robot

ROBOT = load_robot("ur5_paper")


@pytest.mark.parametrize("gain_set", sorted(GAIN_SETS))
@pytest.mark.parametrize("name", LAW_NAMES)
def test_every_law_passes(name: str, gain_set: str) -> None:
    check_law(make_law(name, ROBOT, gain_set=gain_set))


def test_a_law_for_another_arm_passes() -> None:
    panda = load_robot("panda")
    check_law(make_law("pd", panda, kp=np.full(7, 50.0), kd=np.full(7, 5.0)), batch=3, seed=1)


class _Unsaturated(PDLaw):
    def step(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any) -> tuple[Any, Any]:
        return self.pd_torque(xp, q_d - q, qd_d - qd), state


class _Mutating(PDLaw):
    def step(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any) -> tuple[Any, Any]:
        q += 0.0 * q + 1e-3  # in place: the caller's array
        return super().step(xp, state, q, qd, q_d, qd_d, qdd_d)


class _Coupled(PDLaw):
    def step(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any) -> tuple[Any, Any]:
        tau, state = super().step(xp, state, q, qd, q_d, qd_d, qdd_d)
        return self.saturate(xp, tau + 1e-3 * tau.mean()), state  # rows leak into each other


class _WrongState(PIDLaw):
    def step(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any) -> tuple[Any, Any]:
        tau, state = super().step(xp, state, q, qd, q_d, qd_d, qdd_d)
        return tau, state[:, :-1]


class _NumpyOnly(PDLaw):
    def step(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any) -> tuple[Any, Any]:
        tau, state = super().step(xp, state, q, qd, q_d, qd_d, qdd_d)
        return (tau if xp is np else tau + 1e-3), state


class _BadParams(PDLaw):
    @property
    def params(self) -> dict[str, Any]:
        return {"kp": self.kp}  # an ndarray: not JSON


def _pd(cls: type[PDLaw]) -> PDLaw:
    return cls(6, 1e-3, ROBOT.torque_limit_nm)


@pytest.mark.parametrize(
    ("law", "message"),
    [
        (_pd(_Unsaturated), "huge errors give non-finite or unsaturated torques"),
        (_pd(_Mutating), "changed its inputs"),
        (_pd(_Coupled), "row 0 alone differs"),
        (_pd(_WrongState), r"next state is not a finite \(4, 6\) array"),
        (_pd(_NumpyOnly), "in torch differs from numpy"),
        (_pd(_BadParams), "params are not plain JSON"),
        (PDLaw(6, 0.0, ROBOT.torque_limit_nm), "period_s is 0.0"),
        (PDLaw(6, 1e-3, -ROBOT.torque_limit_nm), "torque_limit_nm .* is not \\(6,\\) > 0"),
    ],
    ids=["unsaturated", "mutating", "coupled", "state-shape", "numpy-only", "params", "period", "limits"],
)
def test_broken_laws_are_named(law: PDLaw, message: str) -> None:
    with pytest.raises(LawCheckError, match=f"^law '{law.name}': .*{message}"):
        check_law(law)
