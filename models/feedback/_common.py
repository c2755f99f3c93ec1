"""Helpers shared by the laws: gains checked against the robot, constants in the caller's namespace,
and the nominal rigid-body model that SMC, H-infinity and MRAC use (models.dynamics), in numpy or torch."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from models.dynamics import RneDynamics

if TYPE_CHECKING:  # torch is imported only when a law is traced
    from models.dynamics.torch_rne import RateMap, SpatialRne
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


@dataclass
class SharedId:
    """A caller's own ID request at the law's position, run in the same pass as the law's next torch call.

    ``SpatialRne.inverse_dynamics_shared`` semantics: ID(position, rates @ qd_map, rates @ qdd_map + offset)
    times ``scale``; when ``position`` is not the law's q, it runs as a second pass.
    """

    position: Any
    rates: Any
    rate_map: RateMap
    scale: np.ndarray | None = None


class NominalModel:
    """The nominal rigid-body model of the robot (models.dynamics): numpy through ``RneDynamics``, torch
    through the one traceable RNE (``SpatialRne``, a small ONNX graph).

    Laws that need model terms call it inside ``step`` so the same definition traces to ONNX. A caller
    tracing a graph around the law (models.lmpc.structured) may set ``pending`` to a ``SharedId``: the
    law's next torch call then runs both in one RNE pass and leaves the caller's torque in
    ``pending_result``.
    """

    def __init__(self, robot: RobotModel) -> None:
        self.robot = robot
        self.dynamics = RneDynamics(robot)
        self._torch_rne: SpatialRne | None = None
        self.pending: SharedId | None = None
        self.pending_result: Any = None

    @property
    def torch_rne(self) -> SpatialRne:
        if self._torch_rne is None:
            from models.dynamics.torch_rne import SpatialRne

            self._torch_rne = SpatialRne(self.robot)
        return self._torch_rne

    def inverse_dynamics(self, xp: Any, q: Any, qd: Any, qdd: Any) -> Any:
        """M(q) qdd + C(q, qd) qd + G(q), (B, N)."""
        if xp is np:
            return self.dynamics.inverse_dynamics(q, qd, qdd)
        return self._torch(q, (qd, qdd))

    def gravity(self, xp: Any, q: Any) -> Any:
        """G(q), (B, N)."""
        if xp is np:
            return self.dynamics.gravity(q)
        return self._torch(q, None)

    def _torch(self, q: Any, rates: tuple[Any, Any] | None) -> Any:
        import torch

        rne, request, self.pending = self.torch_rne, self.pending, None
        n = self.robot.n_joints
        eye, zero = np.eye(n), np.zeros((n, n))
        if request is not None and request.position is not q:  # another position: its own pass
            self.pending_result = rne.inverse_dynamics_shared(
                request.position, request.rates, [request.rate_map], [request.scale]
            )[0]
            request = None
        if request is None:
            return rne.gravity_torque(q) if rates is None else rne.inverse_dynamics(q, *rates)
        qd_map, qdd_map, offset = request.rate_map
        width = np.shape(qd_map)[0]
        if rates is None:  # G(q) and the caller's ID: the law's rate set is all zero
            own, inputs = None, request.rates
            theirs = request.rate_map
        else:
            inputs = torch.cat([rates[0], rates[1], request.rates], 1)
            own = (np.vstack([eye, zero, np.zeros((width, n))]), np.vstack([zero, eye, np.zeros((width, n))]), None)
            pad = np.zeros((2 * n, n))
            theirs = (np.vstack([pad, qd_map]), np.vstack([pad, qdd_map]), offset)
        law, caller = rne.inverse_dynamics_shared(q, inputs, [own, theirs], [None, request.scale])
        self.pending_result = caller
        return law

    def mass_matrix_diagonal(self, q: np.ndarray) -> np.ndarray:
        """diag M(q) at one configuration (N,), numpy; used to size per-joint nominal plants."""
        return np.diag(self.dynamics.mass_matrix(np.asarray(q, float))).copy()
