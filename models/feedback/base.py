"""The feedback-law interface: one pure step with explicit state, for one robot or a batch.

A law is ``tau_fb, next_state = law.step(xp, state, q, qd, q_d, qd_d, qdd_d)`` where every array
has a leading batch axis (B, ...) and ``xp`` is the array namespace (numpy for simulation and the
MPC, torch when tracing the same definition to an ONNX step graph). The state is one flat float
array (B, state_size) so that the ONNX graph, the runtime and the dataset all carry it the same way.

Errors are e = q_d - q, e_dot = qd_d - qd (the paper's sign: positive stiffness d(phi)/de > 0).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # torch is imported only when a law is traced
    from models.dynamics.torch_rne import RateMap


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


class FeedbackLaw(ABC):
    """Base of the six laws. Subclasses set the class attribute ``name`` and implement ``step``."""

    name: str = ""

    def __init__(self, n_joints: int, period_s: float, torque_limit_nm: np.ndarray) -> None:
        self.n_joints = n_joints
        self.period_s = float(period_s)
        self.torque_limit_nm = np.asarray(torque_limit_nm, dtype=np.float64)

    # --- what every law declares -------------------------------------------------------------
    @property
    def state_size(self) -> int:
        """Length of the flat state vector (0 for a static law such as PD)."""
        return 0

    #: Where the law keeps the torque actually applied last cycle, if its observer needs it (ADRC).
    #: A caller that applies a different torque (HMPC, LMPC, a safety clamp) writes it there.
    applied_torque_slice: slice | None = None

    @property
    def params(self) -> dict[str, Any]:
        """JSON-serializable parameters actually used (paper values and interpretations)."""
        return {}

    def initial_state(self, q0: np.ndarray) -> np.ndarray:
        """State at the start of a run, for start positions q0 (B, N)."""
        return np.zeros((np.atleast_2d(q0).shape[0], self.state_size))

    @abstractmethod
    def step(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any) -> tuple[Any, Any]:
        """One control period: (tau_fb (B, N) saturated to the torque limits, next state (B, S))."""

    def step_sharing_id(
        self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any, shared: SharedId | None
    ) -> tuple[Any, Any, Any]:
        """``step`` traced with a caller's own ID request (``shared``, torch only): (tau_fb, next state, the
        request's torque or None). A law with a nominal model (H-infinity, SMC) runs the request in its own
        RNE pass; here the law has none, so the caller computes it (None)."""
        tau_fb, next_state = self.step(xp, state, q, qd, q_d, qd_d, qdd_d)
        return tau_fb, next_state, None

    def error_features(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any) -> Any:
        """The law's error vector E (Eq. 15) used by the MPC cost: here [e, e_dot] (B, 2N)."""
        return xp.concatenate([q_d - q, qd_d - qd], -1)

    # --- helpers ------------------------------------------------------------------------------
    def saturate(self, xp: Any, tau: Any) -> Any:
        limit = self.torque_limit_nm if xp is np else xp.as_tensor(self.torque_limit_nm, dtype=tau.dtype)
        return xp.minimum(xp.maximum(tau, -limit), limit)

    def with_applied_torque(self, state: np.ndarray, tau_applied: np.ndarray) -> np.ndarray:
        """The state with the last applied torque recorded (no-op for laws that do not use it)."""
        if self.applied_torque_slice is None:
            return state
        state = state.copy()
        state[:, self.applied_torque_slice] = tau_applied
        return state
