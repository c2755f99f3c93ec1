"""Helpers shared by the laws: gains checked against the robot, constants in the caller's namespace,
and the nominal rigid-body model (one RNEIDA call) that SMC and H-infinity use, in numpy or torch."""

from __future__ import annotations

from typing import Any

import numpy as np

from models.dynamics.rne import ChainArrays, rneida
from models.errors import ModelInputError
from models.robots import RobotModel


def joint_vector(law: str, field: str, value: Any, n_joints: int, paper_value: np.ndarray | None = None) -> np.ndarray:
    """A per-joint gain as a float (N,) array; the paper's 6-vector only fits a 6-joint robot."""
    if value is None:
        if paper_value is None or len(paper_value) != n_joints:
            raise ModelInputError(
                f"law '{law}': the paper's {field} has {0 if paper_value is None else len(paper_value)} joints, "
                f"the robot has {n_joints}; pass {field} explicitly"
            )
        value = paper_value
    array = np.asarray(value, dtype=np.float64)
    if array.ndim == 0:
        array = np.full(n_joints, float(array))
    if array.shape != (n_joints,) or not np.all(np.isfinite(array)):
        raise ModelInputError(
            f"law '{law}': {field} must be {n_joints} finite numbers, got {np.asarray(value).tolist()}"
        )
    return array


def const(xp: Any, value: np.ndarray) -> Any:
    """A numpy constant in the caller's namespace (float64 tensors when tracing with torch)."""
    if xp is np:
        return value
    return xp.as_tensor(np.asarray(value, dtype=np.float64))


def sat(xp: Any, x: Any) -> Any:
    """Unit saturation sat(x) = clip(x, -1, 1) (the SMC boundary layer)."""
    return xp.clip(x, -1.0, 1.0)


class NominalModel:
    """The nominal rigid-body model of the robot, evaluated by the project's RNEIDA in numpy or torch.

    Laws that need model terms call it inside ``step`` so the same definition traces to ONNX.
    """

    def __init__(self, robot: RobotModel) -> None:
        self.robot = robot
        self._chains: dict[str, ChainArrays] = {"numpy": ChainArrays.from_robot(robot)}

    def _chain(self, xp: Any) -> ChainArrays:
        key = "numpy" if xp is np else "torch"
        if key not in self._chains:
            self._chains[key] = ChainArrays.from_robot(self.robot, to_array=lambda a: xp.as_tensor(a, dtype=xp.float64))
        return self._chains[key]

    def inverse_dynamics(self, xp: Any, q: Any, qd: Any, qdd: Any) -> Any:
        """M(q) qdd + C(q, qd) qd + G(q), (B, N), one RNEIDA call."""
        chain = self._chain(xp)
        return rneida(xp, chain, q, qd, qdd, chain.gravity)

    def gravity(self, xp: Any, q: Any) -> Any:
        """G(q), (B, N)."""
        zero = xp.zeros_like(q)
        return self.inverse_dynamics(xp, q, zero, zero)

    def mass_matrix_diagonal(self, q: np.ndarray) -> np.ndarray:
        """diag M(q) at one configuration (N,), numpy; used to size per-joint nominal plants."""
        from models.dynamics.rne import mass_matrix_and_bias

        mass_matrix, _ = mass_matrix_and_bias(np, self._chains["numpy"], np.atleast_2d(q), np.zeros((1, len(q))))
        return np.diag(mass_matrix[0]).copy()
