"""``check_plant``: does an implementation behave as :class:`~sim_target.plant_protocol.TargetPlant` says?

In the manner of Gymnasium's ``check_env`` (and ``drivers.checks.check_joint_bus`` on the other
side of the bus): run it against any plant the emulated drives may step (``PybulletPlant``,
``sim_target.testing.fake_plant.FakePlant``, a new one) before trusting a HIL run to it::

    reset(q0) -> state() -> step(0, all braked) x3 -> step(small torque, free) x3
    -> reset(q0) and the same steps again (deterministic) -> reset()

and raises :class:`PlantCheckError` naming the first broken promise. The plant must be noise-free
(encoder noise off) for the comparisons to hold.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["PlantCheckError", "check_plant"]

_FIELDS = ("position_rad", "velocity_rad_s", "torque_nm")


class PlantCheckError(AssertionError):
    """The plant under check broke a promise of the TargetPlant protocol (the message says which)."""


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise PlantCheckError(message)


def _check_state(state: Any, n: int, where: str) -> None:
    for name in (*_FIELDS, "time_s"):
        _require(hasattr(state, name), f"{where}: returned {type(state).__name__} without '{name}'")
    for name in _FIELDS:
        value = getattr(state, name)
        _require(
            isinstance(value, np.ndarray) and value.shape == (n,) and value.dtype.kind == "f",
            f"{where}: {name} is not a float ndarray of shape ({n},)",
        )
        _require(bool(np.all(np.isfinite(value))), f"{where}: {name} is not finite: {value.tolist()}")
    _require(isinstance(state.time_s, float | int) and math.isfinite(state.time_s), f"{where}: time_s is not finite")


def _snapshot(state: Any) -> tuple[np.ndarray, ...]:
    return tuple(np.array(getattr(state, name), float) for name in _FIELDS)


def check_plant(
    plant: Any,
    position_rad: np.ndarray | None = None,
    torque_nm: float = 1e-3,
    brake_hold_rad: float = 1e-4,
) -> None:
    """Check ``plant`` (left reset to its initial position). ``position_rad``: the start position
    (default: where ``reset()`` puts it); ``torque_nm``: the small test torque, inside every joint's
    limit; ``brake_hold_rad``: how far a braked joint may move over three periods."""
    n, period_s = getattr(plant, "n_joints", None), getattr(plant, "period_s", None)
    _require(isinstance(n, int) and n > 0, f"n_joints is {n!r}, expected a positive int")
    _require(
        isinstance(period_s, float | int) and math.isfinite(period_s) and period_s > 0,
        f"period_s is {period_s!r}, expected a finite number > 0",
    )
    assert isinstance(n, int) and period_s is not None  # for the type checker: checked just above
    for method in ("reset", "state", "step"):
        _require(callable(getattr(plant, method, None)), f"no method {method}()")

    default = plant.reset()
    _check_state(default, n, "reset()")
    q0 = np.array(default.position_rad, float) if position_rad is None else np.asarray(position_rad, float)
    start = plant.reset(q0)
    _check_state(start, n, "reset(q0)")
    _require(start.time_s == 0.0, f"reset(q0): time_s is {start.time_s}, expected 0")
    _require(np.allclose(start.position_rad, q0, atol=1e-9), "reset(q0): position_rad is not q0")
    _require(np.allclose(start.velocity_rad_s, 0.0, atol=1e-9), "reset(q0): the arm is not at rest")
    again = plant.state()
    _check_state(again, n, "state()")
    _require(
        all(np.array_equal(a, b) for a, b in zip(_snapshot(again), _snapshot(start), strict=True))
        and again.time_s == start.time_s,
        "state() differs from what reset(q0) returned (it must not advance the plant)",
    )

    def run() -> list[tuple[np.ndarray, ...]]:
        seen = []
        braked, free = np.ones(n, dtype=bool), np.zeros(n, dtype=bool)
        for k in range(1, 7):
            brake = braked if k <= 3 else free
            command = np.zeros(n) if k <= 3 else np.full(n, torque_nm)
            state = plant.step(command, brake)
            where = f"step {k} ({'all braked' if k <= 3 else 'free, small torque'})"
            _check_state(state, n, where)
            _require(
                math.isclose(state.time_s, k * period_s, rel_tol=1e-9, abs_tol=1e-12),
                f"{where}: time_s is {state.time_s}, expected {k} x period_s = {k * period_s}",
            )
            applied = np.where(brake, 0.0, command)
            _require(
                np.allclose(state.torque_nm, applied, atol=1e-12),
                f"{where}: torque_nm {state.torque_nm.tolist()} is not the torque applied ({applied.tolist()})",
            )
            if k <= 3:
                moved = float(np.max(np.abs(state.position_rad - q0)))
                _require(moved <= brake_hold_rad, f"{where}: a braked joint moved {moved:.3g} rad")
            last = plant.state()
            _require(
                all(np.array_equal(a, b) for a, b in zip(_snapshot(last), _snapshot(state), strict=True)),
                f"{where}: state() differs from what step() returned",
            )
            seen.append(_snapshot(state))
        return seen

    first = run()
    plant.reset(q0)
    second = run()
    for k, (a, b) in enumerate(zip(first, second, strict=True), start=1):
        _require(
            all(np.array_equal(x, y) for x, y in zip(a, b, strict=True)),
            f"step {k}: not reproducible (reset(q0) and the same commands gave another state)",
        )
    plant.reset()
