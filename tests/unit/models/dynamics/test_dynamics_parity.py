"""One dynamics entry point: the numpy RNE, pinocchio and the torch RNE agree; forward dynamics is rnefda."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from models.dynamics import backends as dynamics_backends
from models.dynamics import make_dynamics
from models.dynamics.torch_rne import SpatialRne
from models.robots import load_robot

ROBOTS = ["ur5_paper", "ur5", "panda"]


def _states(n: int, rows: int = 9, seed: int = 3) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    return tuple(rng.normal(size=(rows, n)) for _ in range(3))


@pytest.mark.parametrize("name", ROBOTS)
def test_numpy_rne_pinocchio_and_torch_rne_agree(name: str) -> None:
    robot = load_robot(name)
    q, qd, qdd = _states(robot.n_joints)
    own, pin = make_dynamics(robot, "rne"), make_dynamics(robot, "pinocchio")
    rne = SpatialRne(robot)
    expected = pin.inverse_dynamics(q, qd, qdd)
    scale = max(1.0, float(np.abs(expected).max()))
    np.testing.assert_allclose(own.inverse_dynamics(q, qd, qdd), expected, rtol=0, atol=1e-11 * scale)
    got = rne.inverse_dynamics(*(torch.as_tensor(a) for a in (q, qd, qdd))).numpy()
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-11 * scale)
    np.testing.assert_allclose(
        rne.gravity_torque(torch.as_tensor(q)).numpy(), pin.gravity(q), rtol=0, atol=1e-11 * scale
    )
    tau = expected + 0.3
    np.testing.assert_allclose(own.forward_dynamics(q, qd, tau), pin.forward_dynamics(q, qd, tau), rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("name", ROBOTS)
def test_shared_rate_sets_are_one_pass_with_their_own_scales(name: str) -> None:
    robot = load_robot(name)
    n = robot.n_joints
    q, qd, qdd = _states(n, seed=4)
    _, qd2, qdd2 = _states(n, seed=5)
    own = make_dynamics(robot, "rne")
    rne = SpatialRne(robot)
    z = torch.as_tensor(np.concatenate([qd, qdd, qd2, qdd2], 1))
    eye, zero = np.eye(n), np.zeros((n, n))
    first = (np.vstack([eye, zero, zero, zero]), np.vstack([zero, eye, zero, zero]), None)
    offset = np.linspace(-1.0, 1.0, n)
    second = (np.vstack([zero, zero, eye, zero]), np.vstack([zero, zero, zero, eye]), offset)
    scale = np.linspace(0.5, 2.0, n)
    a, b = rne.inverse_dynamics_shared(torch.as_tensor(q), z, [first, second], [None, scale])
    np.testing.assert_allclose(a.numpy(), own.inverse_dynamics(q, qd, qdd), rtol=0, atol=1e-10)
    np.testing.assert_allclose(b.numpy(), scale * own.inverse_dynamics(q, qd2, qdd2 + offset), rtol=0, atol=1e-10)
    (g,) = rne.inverse_dynamics_shared(torch.as_tensor(q), None, [None])
    np.testing.assert_allclose(g.numpy(), own.gravity(q), rtol=0, atol=1e-10)


def test_forward_dynamics_is_rnefda(monkeypatch: pytest.MonkeyPatch) -> None:
    """The paper's Alg. 1 is what RneDynamics.forward_dynamics runs (not an inline M^-1 (tau - h))."""
    robot = load_robot("ur5_paper")
    calls = []
    real = dynamics_backends.rnefda

    def spy(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(dynamics_backends, "rnefda", spy)
    q, qd, tau = _states(6, rows=2)
    make_dynamics(robot, "rne").forward_dynamics(q, qd, tau)
    assert calls == [1]


def test_forward_dynamics_derivatives_agree_between_backends() -> None:
    robot = load_robot("ur5_paper")
    q, qd, tau = _states(6, rows=4, seed=6)
    own = make_dynamics(robot, "rne").forward_dynamics_derivatives(q, qd, tau)
    pin = make_dynamics(robot, "pinocchio").forward_dynamics_derivatives(q, qd, tau)
    for a, b in zip(own, pin, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-7 * max(1.0, float(np.abs(b).max())))


def test_hmpc_predictor_is_the_dynamics_backend() -> None:
    from models.errors import ModelInputError
    from models.hmpc.prediction import make_predictor

    robot = load_robot("ur5_paper")
    q, qd, tau = _states(6, rows=3, seed=7)
    for backend in ("rne", "pinocchio"):
        predictor = make_predictor(robot, backend)
        expected = make_dynamics(robot, backend).forward_dynamics(q, qd, tau)
        np.testing.assert_allclose(predictor.acceleration(q, qd, tau), expected, rtol=0, atol=1e-9)
        np.testing.assert_allclose(predictor.acceleration(q[:1], qd[:1], tau[:1]), expected[:1], rtol=0, atol=1e-9)
    with pytest.raises(ModelInputError, match="hmpc backend: unknown 'mujoco'"):
        make_predictor(robot, "mujoco")
