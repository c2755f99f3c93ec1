"""The paper's recursive Newton-Euler algorithms, written here (Sec. II, Alg. 1 and 2).

RNEIDA (Alg. 2): forward recursion of angular velocity/acceleration and linear acceleration of
each joint frame and link COM, in body coordinates (Eqs. 3-6); backward recursion of constraint
forces and moments (Eqs. 7-10); joint torque as the moment's projection on the joint axis (Eq. 12).
Gravity enters as a fictitious base acceleration -g. An external wrench on the end effector
initializes the backward recursion (Eqs. 8, 11).

RNEFDA (Alg. 1): h(q, q_dot) from one RNEIDA call with q_ddot = 0, the mass matrix column by column
from N calls with unit accelerations (no velocity, no gravity), then q_ddot = M^-1 (tau - h).
All N + 1 calls run as one batched RNEIDA pass.

Every function is vectorized over a leading batch axis and written against an array namespace
``xp`` (numpy, or torch for tracing a law to ONNX), using only operations both provide.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from models.robots import RobotModel


@dataclass(frozen=True, eq=False)
class ChainArrays:
    """The robot's constant parameters as arrays of one namespace (numpy or torch)."""

    joint_rotation: Any  # (N, 3, 3)
    joint_translation: Any  # (N, 3)
    joint_axis: Any  # (N, 3)
    axis_cross: Any  # (N, 3, 3) skew(axis)
    axis_outer: Any  # (N, 3, 3) axis axis^T
    axis_perp: Any  # (N, 3, 3) I - axis axis^T
    mass: Any  # (N,)
    com: Any  # (N, 3)
    inertia: Any  # (N, 3, 3)
    ee_rotation: Any  # (3, 3)
    ee_translation: Any  # (3,)
    gravity: Any  # (3,)
    translation_skew: Any  # (N, 3, 3) skew(joint_translation): w x p = w @ skew(p)
    com_skew: Any  # (N, 3, 3) skew(com)
    ee_translation_skew: Any  # (3, 3)
    n_joints: int

    @classmethod
    def from_robot(cls, robot: RobotModel, to_array: Any = np.asarray) -> ChainArrays:
        axis = robot.joint_axis
        outer = np.einsum("ni,nj->nij", axis, axis)
        values = [
            robot.joint_rotation,
            robot.joint_translation,
            axis,
            _skew(axis),
            outer,
            np.eye(3) - outer,
            robot.mass_kg,
            robot.com_m,
            robot.inertia_kg_m2,
            robot.ee_rotation,
            robot.ee_translation,
            robot.gravity_m_s2,
            _skew(robot.joint_translation),
            _skew(robot.com_m),
            _skew(robot.ee_translation),
        ]
        return cls(*[to_array(np.asarray(v, dtype=np.float64)) for v in values], n_joints=robot.n_joints)


def _skew(v: np.ndarray) -> np.ndarray:
    """skew(v) with skew(v) @ w = v x w, for v of shape (..., 3)."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return out - np.swapaxes(out, -1, -2)


def _cross(xp: Any, a: Any, b: Any) -> Any:
    """Batched cross product over the last axis (numpy and torch alike)."""
    return xp.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        -1,
    )


def _matvec(xp: Any, m: Any, v: Any) -> Any:
    return (m @ v[..., None])[..., 0]


def _matTvec(xp: Any, m: Any, v: Any) -> Any:
    return (v[..., None, :] @ m)[..., 0, :]


def joint_rotations(xp: Any, chain: ChainArrays, q: Any) -> list[Any]:
    """R_{i-1,i}(q_i): orientation of frame i in frame i-1 (Rodrigues about the joint axis)."""
    rotations = []
    for i in range(chain.n_joints):
        s, c = xp.sin(q[..., i])[..., None, None], xp.cos(q[..., i])[..., None, None]
        about_axis = c * chain.axis_perp[i] + chain.axis_outer[i] + s * chain.axis_cross[i]
        rotations.append(chain.joint_rotation[i] @ about_axis)
    return rotations


def rneida(
    xp: Any,
    chain: ChainArrays,
    q: Any,
    qd: Any,
    qdd: Any,
    gravity: Any,
    ee_wrench: Any | None = None,
) -> Any:
    """Alg. 2: joint torques (B, N) for states (B, N).

    ``gravity`` is (B, 3) or (3,) in the base frame; ``ee_wrench`` (B, 6) = [force, moment] that the
    environment applies to the end effector, in the end-effector frame (pinocchio's convention:
    tau = ID(q, qd, qdd) - J^T wrench).
    """
    n = chain.n_joints
    rotations = joint_rotations(xp, chain, q)
    omega = q[..., :1] * 0.0 + 0.0 * chain.gravity  # (B, 3) zeros in q's namespace and dtype
    omega_dot = omega
    accel = omega - gravity  # the base frame origin accelerates at -g (fictitious), (B, 3)
    forces, moments = [], []
    for i in range(n):
        rot = rotations[i]
        # Eq. 5: acceleration of frame i's origin, from frame i-1's motion, then into frame i.
        # (Cross products with a constant vector are one product with its skew matrix: w x p = w @ skew(p).)
        p_skew = chain.translation_skew[i]
        accel = _matTvec(xp, rot, accel + omega_dot @ p_skew + _cross(xp, omega, omega @ p_skew))
        # Eqs. 3-4: angular velocity and acceleration in frame i.
        omega_parent = _matTvec(xp, rot, omega)
        rate = qd[..., i : i + 1]
        omega = omega_parent + chain.joint_axis[i] * rate
        omega_dot = (
            _matTvec(xp, rot, omega_dot)
            + chain.joint_axis[i] * qdd[..., i : i + 1]
            + (omega_parent @ chain.axis_cross[i]) * rate  # omega_parent x (axis qd_i)
        )
        # Eq. 6: COM acceleration; Newton and Euler equations of link i.
        c_skew = chain.com_skew[i]
        accel_com = accel + omega_dot @ c_skew + _cross(xp, omega, omega @ c_skew)
        forces.append(chain.mass[i] * accel_com)
        inertia = chain.inertia[i]
        moments.append(_matvec(xp, inertia, omega_dot) + _cross(xp, omega, _matvec(xp, inertia, omega)))

    # Backward recursion (Eqs. 7-10), starting from the end effector's reaction (Eqs. 8, 11).
    if ee_wrench is None:
        f_next = xp.zeros_like(accel)
        n_next = xp.zeros_like(accel)
    else:
        f_next = -_matvec(xp, chain.ee_rotation, ee_wrench[..., :3])
        n_next = -_matvec(xp, chain.ee_rotation, ee_wrench[..., 3:])
    p_next_skew = chain.ee_translation_skew
    rot_next = None
    torques = [None] * n
    for i in range(n - 1, -1, -1):
        f_child = f_next if rot_next is None else _matvec(xp, rot_next, f_next)
        n_child = n_next if rot_next is None else _matvec(xp, rot_next, n_next)
        f_i = f_child + forces[i]
        # c x F = -(F @ skew(c)), p x f = -(f @ skew(p))
        n_i = moments[i] + n_child - forces[i] @ chain.com_skew[i] - f_child @ p_next_skew
        torques[i] = n_i @ chain.joint_axis[i]  # Eq. 12
        f_next, n_next, p_next_skew, rot_next = f_i, n_i, chain.translation_skew[i], rotations[i]
    return xp.stack(torques, -1)


def rnefda(
    xp: Any,
    chain: ChainArrays,
    q: Any,
    qd: Any,
    tau: Any,
    ee_wrench: Any | None = None,
    gravity: Any | None = None,
) -> Any:
    """Alg. 1: joint accelerations (B, N) from torques, via h and M built by RNEIDA calls."""
    mass_matrix, bias = mass_matrix_and_bias(xp, chain, q, qd, ee_wrench, gravity)
    return xp.linalg.solve(mass_matrix, (tau - bias)[..., None])[..., 0]


def mass_matrix_and_bias(
    xp: Any, chain: ChainArrays, q: Any, qd: Any, ee_wrench: Any | None = None, gravity: Any | None = None
) -> tuple[Any, Any]:
    """M(q) (B, N, N) and h(q, qd) = C qd + G - J^T wrench (B, N), in one batched RNEIDA pass."""
    n = chain.n_joints
    batch = q.shape[0]
    g = chain.gravity if gravity is None else gravity
    eye = xp.eye(n, dtype=q.dtype)
    # Row 0 of each group: h with (qd, qdd=0, g, wrench); rows 1..N: unit accelerations, no qd, no g.
    q_all = xp.reshape(xp.stack([q] * (n + 1), 1), (batch * (n + 1), n))
    qd_all = xp.reshape(xp.concatenate([qd[:, None, :], xp.zeros_like(q)[:, None, :] + 0.0 * eye], 1), (-1, n))
    qdd_all = xp.reshape(xp.concatenate([xp.zeros_like(q)[:, None, :], xp.zeros_like(q)[:, None, :] + eye], 1), (-1, n))
    g_rows = xp.concatenate([xp.ones_like(q[:, :1]), xp.zeros_like(q)], 1)  # (B, N+1)
    g_all = xp.reshape(g_rows[..., None] * g, (-1, 3))
    wrench_all = None
    if ee_wrench is not None:
        w_rows = xp.concatenate([ee_wrench[:, None, :], xp.zeros_like(ee_wrench)[:, None, :] * g_rows[:, 1:, None]], 1)
        wrench_all = xp.reshape(w_rows, (-1, 6))
    tau = xp.reshape(rneida(xp, chain, q_all, qd_all, qdd_all, g_all, wrench_all), (batch, n + 1, n))
    bias = tau[:, 0, :]
    mass_matrix = xp.swapaxes(tau[:, 1:, :], -1, -2)  # column j = torque for unit acceleration j
    return mass_matrix, bias
