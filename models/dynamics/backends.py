"""Two interchangeable dynamics backends behind one interface.

``RneDynamics`` runs this project's own RNEIDA/RNEFDA (rne.py); ``PinocchioDynamics`` runs
pinocchio's rnea/crba/aba on the same robot description. Every method accepts a single state
(shape (N,)) or a batch (shape (B, N)) and returns the matching shape.

    dyn = make_dynamics(load_robot("ur5_paper"), backend="rne")
    tau = dyn.inverse_dynamics(q, qd, qdd)
    qdd = dyn.forward_dynamics(q, qd, tau)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from models.dynamics.rne import ChainArrays, mass_matrix_and_bias, rnefda, rneida
from models.errors import ModelInputError
from models.robots import RobotModel

COMPLEX_STEP = 1e-30


class Dynamics(Protocol):
    """Rigid-body dynamics M(q) qdd + C(q, qd) qd + G(q) = tau + J^T wrench."""

    robot: RobotModel
    n_joints: int

    def inverse_dynamics(
        self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, ee_wrench: np.ndarray | None = None
    ) -> np.ndarray: ...
    def mass_matrix(self, q: np.ndarray) -> np.ndarray: ...
    def nonlinear_effects(self, q: np.ndarray, qd: np.ndarray, ee_wrench: np.ndarray | None = None) -> np.ndarray: ...
    def gravity(self, q: np.ndarray) -> np.ndarray: ...
    def forward_dynamics(
        self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray, ee_wrench: np.ndarray | None = None
    ) -> np.ndarray: ...
    def forward_dynamics_derivatives(
        self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]: ...


def _batched(*arrays: np.ndarray) -> tuple[bool, list[np.ndarray]]:
    single = np.ndim(arrays[0]) == 1
    return single, [_rows(a) for a in arrays]


def _rows(array: np.ndarray) -> np.ndarray:
    return np.atleast_2d(np.asarray(array, dtype=np.float64))


def _optional_rows(array: np.ndarray | None) -> np.ndarray | None:
    """An optional input (the end-effector wrench) batched like the others."""
    return None if array is None else _rows(array)


def _unbatch(single: bool, value: np.ndarray) -> np.ndarray:
    return value[0] if single else value


class RneDynamics:
    """The paper's recursive Newton-Euler algorithms (this project's own code), in numpy."""

    def __init__(self, robot: RobotModel) -> None:
        self.robot = robot
        self.n_joints = robot.n_joints
        self.chain = ChainArrays.from_robot(robot)

    def inverse_dynamics(
        self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, ee_wrench: np.ndarray | None = None
    ) -> np.ndarray:
        single, (q, qd, qdd) = _batched(q, qd, qdd)
        w = _optional_rows(ee_wrench)
        return _unbatch(single, rneida(np, self.chain, q, qd, qdd, self.chain.gravity, w))

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        single, (q,) = _batched(q)
        mass_matrix, _ = mass_matrix_and_bias(np, self.chain, q, np.zeros_like(q))
        return _unbatch(single, mass_matrix)

    def nonlinear_effects(self, q: np.ndarray, qd: np.ndarray, ee_wrench: np.ndarray | None = None) -> np.ndarray:
        single, (q, qd) = _batched(q, qd)
        w = _optional_rows(ee_wrench)
        zero = np.zeros_like(q)
        return _unbatch(single, rneida(np, self.chain, q, qd, zero, self.chain.gravity, w))

    def gravity(self, q: np.ndarray) -> np.ndarray:
        single, (q,) = _batched(q)
        zero = np.zeros_like(q)
        return _unbatch(single, rneida(np, self.chain, q, zero, zero, self.chain.gravity))

    def forward_dynamics(
        self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray, ee_wrench: np.ndarray | None = None
    ) -> np.ndarray:
        """RNEFDA (Alg. 1): h and M from N + 1 RNEIDA calls (one batched pass), then a solve."""
        single, (q, qd, tau) = _batched(q, qd, tau)
        w = _optional_rows(ee_wrench)
        return _unbatch(single, rnefda(np, self.chain, q, qd, tau, w))

    def forward_dynamics_derivatives(
        self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(qdd, dqdd/dq, dqdd/dqd, dqdd/dtau) for states (K, N), exact.

        d(qdd)/dtau = M^-1 and d(qdd)/d(q, qd) = -M^-1 d(ID)/d(q, qd) at qdd, the RNEIDA partials by
        complex-step differentiation (Im f(x + i h) / h, h = 1e-30: no cancellation error), so they
        agree with pinocchio's analytic ABA derivatives to round-off.
        """
        k, n = q.shape
        mass_matrix, bias = mass_matrix_and_bias(np, self.chain, q, qd)
        m_inv = np.linalg.inv(mass_matrix)
        qdd = np.einsum("kij,kj->ki", m_inv, tau - bias)
        # RNEIDA at (q, qd, qdd) perturbed along each q_i and each qd_i by i*h: 2N complex rows per state.
        eye = np.eye(n) * (1j * COMPLEX_STEP)
        q_rows = np.concatenate([q[:, None, :] + eye, np.broadcast_to(q[:, None, :], (k, n, n))], 1)
        qd_rows = np.concatenate([np.broadcast_to(qd[:, None, :], (k, n, n)), qd[:, None, :] + eye], 1)
        qdd_rows = np.broadcast_to(qdd[:, None, :], (k, 2 * n, n)).astype(complex)
        tau_rows = rneida(
            np, self.chain, q_rows.reshape(-1, n), qd_rows.reshape(-1, n), qdd_rows.reshape(-1, n), self.chain.gravity
        )
        partials = tau_rows.imag.reshape(k, 2 * n, n) / COMPLEX_STEP  # row i: d(ID)/d(x_i)
        d_id_dq = np.swapaxes(partials[:, :n], 1, 2)
        d_id_dqd = np.swapaxes(partials[:, n:], 1, 2)
        return qdd, -m_inv @ d_id_dq, -m_inv @ d_id_dqd, m_inv

    def mass_matrix_and_bias(self, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        single, (q, qd) = _batched(q, qd)
        mass_matrix, bias = mass_matrix_and_bias(np, self.chain, q, qd)
        return _unbatch(single, mass_matrix), _unbatch(single, bias)


def build_pinocchio_model(robot: RobotModel) -> Any:  # a pinocchio.Model (pinocchio ships no type stubs)
    """A pinocchio model of exactly this description (so payload/scaling variants carry over)."""
    import pinocchio as pin

    model = pin.Model()
    model.name = robot.name
    parent = 0
    for i in range(robot.n_joints):
        placement = pin.SE3(robot.joint_rotation[i], robot.joint_translation[i])
        joint = pin.JointModelRevoluteUnaligned(*robot.joint_axis[i])
        parent = model.addJoint(parent, joint, placement, robot.joint_names[i])
        inertia = pin.Inertia(float(robot.mass_kg[i]), robot.com_m[i], robot.inertia_kg_m2[i])
        model.appendBodyToJoint(parent, inertia, pin.SE3.Identity())
    model.gravity = pin.Motion(np.asarray(robot.gravity_m_s2, float), np.zeros(3))
    ee = pin.SE3(robot.ee_rotation, robot.ee_translation)
    model.addFrame(pin.Frame("ee", parent, 0, ee, pin.FrameType.OP_FRAME))
    return model


class PinocchioDynamics:
    """pinocchio's rnea / crba / aba behind the same interface (C++; loops over a batch)."""

    def __init__(self, robot: RobotModel) -> None:
        try:
            import pinocchio as pin
        except ImportError as exc:  # pragma: no cover - depends on the install
            raise ModelInputError("backend 'pinocchio': the pin package is not installed (pip install pin)") from exc
        self._pin = pin
        self.robot = robot
        self.n_joints = robot.n_joints
        self.model = build_pinocchio_model(robot)
        self.data = self.model.createData()
        self._pool = None  # built on the first batched forward_dynamics (not pickled)
        self._ee_joint = self.model.njoints - 1
        self._ee_placement = pin.SE3(robot.ee_rotation, robot.ee_translation)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_pool"] = None
        return state

    def _fext(self, wrench: np.ndarray | None) -> Any:  # a pinocchio.StdVec_Force or None (no type stubs)
        if wrench is None:
            return None
        pin = self._pin
        forces = pin.StdVec_Force()
        for _ in range(self.model.njoints):
            forces.append(pin.Force.Zero())
        # wrench in the ee frame -> the same wrench expressed in the last joint's frame
        forces[self._ee_joint] = self._ee_placement.act(pin.Force(wrench[:3], wrench[3:]))
        return forces

    def _each(self, fn: Callable[..., np.ndarray], first: np.ndarray, *arrays: np.ndarray | None) -> np.ndarray:
        """``fn`` on each row of the batch (a None input, the absent wrench, passed as None to every row)."""
        single, (rows_first,) = _batched(first)
        batch = [rows_first] + [_optional_rows(a) for a in arrays]
        rows = [fn(*(None if a is None else a[b] for a in batch)) for b in range(rows_first.shape[0])]
        return _unbatch(single, np.array(rows))

    def inverse_dynamics(
        self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, ee_wrench: np.ndarray | None = None
    ) -> np.ndarray:
        def one(q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, w: np.ndarray | None) -> np.ndarray:
            args = (q, qd, qdd) if w is None else (q, qd, qdd, self._fext(w))
            tau: np.ndarray = self._pin.rnea(self.model, self.data, *args).copy()  # typed: pinocchio has no stubs
            return tau

        return self._each(one, q, qd, qdd, ee_wrench)

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        def one(q: np.ndarray) -> np.ndarray:
            m = self._pin.crba(self.model, self.data, q)
            upper: np.ndarray = np.triu(m) + np.triu(m, 1).T
            return upper

        return self._each(one, q)

    def nonlinear_effects(self, q: np.ndarray, qd: np.ndarray, ee_wrench: np.ndarray | None = None) -> np.ndarray:
        return self.inverse_dynamics(q, qd, np.zeros_like(np.asarray(q, float)), ee_wrench)

    def gravity(self, q: np.ndarray) -> np.ndarray:
        return self._each(lambda q: self._pin.computeGeneralizedGravity(self.model, self.data, q).copy(), q)

    def forward_dynamics(
        self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray, ee_wrench: np.ndarray | None = None
    ) -> np.ndarray:
        if ee_wrench is None and isinstance(q, np.ndarray) and q.ndim == 2:  # a batch: ABA in one C++ call
            qdd: np.ndarray  # typed here: pinocchio has no stubs
            if q.shape[0] == 1:  # one state (the 1 kHz loop): the plain call has less set-up
                qdd = self._pin.aba(self.model, self.data, q[0], qd[0], tau[0])[None].copy()
                return qdd
            # (K, N) C-contiguous transposes to the (N, K) column-major layout pinocchio wants: no copy.
            q, qd, tau = (np.ascontiguousarray(a, dtype=np.float64) for a in (q, qd, tau))
            if self._pool is None:
                # One model/data, one thread: a 1 kHz loop must not wait on thread start-up, and batch
                # labeling gets its parallelism from processes (models.hmpc.batch).
                self._pool = self._pin.ModelPool(self.model, 1)
            qdd = self._pin.abaInParallel(1, self._pool, q.T, qd.T, tau.T).T
            return qdd

        def one(q: np.ndarray, qd: np.ndarray, tau: np.ndarray, w: np.ndarray | None) -> np.ndarray:
            args = (q, qd, tau) if w is None else (q, qd, tau, self._fext(w))
            qdd: np.ndarray = self._pin.aba(self.model, self.data, *args).copy()  # typed: pinocchio has no stubs
            return qdd

        return self._each(one, q, qd, tau, ee_wrench)

    def forward_dynamics_derivatives(
        self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(qdd, dqdd/dq, dqdd/dqd, dqdd/dtau) for states (K, N): pinocchio's analytic ABA derivatives."""
        pin, model, data = self._pin, self.model, self.data
        k, n = q.shape
        qdd = np.empty((k, n))
        d_q, d_qd, d_tau = np.empty((k, n, n)), np.empty((k, n, n)), np.empty((k, n, n))
        for row in range(k):
            # The returned arrays alias pinocchio's data: copy them out before the next call.
            d_q[row], d_qd[row], d_tau[row] = pin.computeABADerivatives(model, data, q[row], qd[row], tau[row])
            qdd[row] = data.ddq
        return qdd, d_q, d_qd, d_tau


BACKENDS: dict[str, Callable[[RobotModel], Dynamics]] = {"rne": RneDynamics, "pinocchio": PinocchioDynamics}


def make_dynamics(robot: RobotModel, backend: str = "rne") -> Dynamics:
    """The dynamics of ``robot`` from the named backend: ``rne`` (own code) or ``pinocchio``."""
    if backend not in BACKENDS:
        raise ModelInputError(f"dynamics backend: unknown '{backend}' (known: {', '.join(BACKENDS)})")
    return BACKENDS[backend](robot)
