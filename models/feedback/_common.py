"""Helpers shared by the laws: gains checked against the robot, constants in the caller's namespace,
and the nominal rigid-body model that SMC, H-infinity and MRAC use (models.dynamics), in numpy or torch."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from models.dynamics import RneDynamics
from models.feedback.base import SharedId

if TYPE_CHECKING:  # torch is imported only when a law is traced
    from models.dynamics.torch_rne import SpatialRne
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
    """The nominal rigid-body model of the robot (models.dynamics): numpy through ``RneDynamics``, torch
    through the one traceable RNE (``SpatialRne``, a small ONNX graph).

    Laws that need model terms call it inside ``step`` so the same definition traces to ONNX. A caller
    tracing a graph around the law (models.lmpc.structured) passes its own ID request (a ``SharedId``) to
    ``FeedbackLaw.step_sharing_id``; the law hands it to ``inverse_dynamics_sharing`` or ``gravity_sharing``,
    which run both in one RNE pass and return the caller's torque beside the law's.
    """

    def __init__(self, robot: RobotModel) -> None:
        self.robot = robot
        self.dynamics = RneDynamics(robot)
        self._torch_rne: SpatialRne | None = None

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
        return self._torch(q, (qd, qdd), None)[0]

    def gravity(self, xp: Any, q: Any) -> Any:
        """G(q), (B, N)."""
        if xp is np:
            return self.dynamics.gravity(q)
        return self._torch(q, None, None)[0]

    def inverse_dynamics_sharing(self, q: Any, qd: Any, qdd: Any, shared: SharedId | None) -> tuple[Any, Any]:
        """Torch only: (the law's ID (B, N), the caller's ``shared`` request's torque or None), one RNE pass."""
        return self._torch(q, (qd, qdd), shared)

    def gravity_sharing(self, q: Any, shared: SharedId | None) -> tuple[Any, Any]:
        """Torch only: (G(q) (B, N), the caller's ``shared`` request's torque or None), one RNE pass."""
        return self._torch(q, None, shared)

    def _torch(self, q: Any, rates: tuple[Any, Any] | None, request: SharedId | None) -> tuple[Any, Any]:
        import torch

        rne = self.torch_rne
        n = self.robot.n_joints
        eye, zero = np.eye(n), np.zeros((n, n))
        caller: Any = None
        if request is not None and request.position is not q:  # another position: its own pass
            alone = rne.inverse_dynamics_shared(request.position, request.rates, [request.rate_map], [request.scale])
            caller = alone[0]
            request = None
        if request is None:
            return (rne.gravity_torque(q) if rates is None else rne.inverse_dynamics(q, *rates)), caller
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
        return law, caller

    def mass_matrix_diagonal(self, q: np.ndarray) -> np.ndarray:
        """diag M(q) at one configuration (N,), numpy; used to size per-joint nominal plants."""
        return np.diag(self.dynamics.mass_matrix(np.asarray(q, float))).copy()
