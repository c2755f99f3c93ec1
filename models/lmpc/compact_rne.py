"""A compact RNEIDA for ONNX export: the same equations as models.dynamics.rne, fewer graph nodes.

Traced with torch, ``rneida`` builds ~1,700 ONNX nodes (component gathers for every cross product),
and onnxruntime's per-node cost then dominates the LMPC cycle of the laws that use the nominal model
(H-infinity: gravity, SMC: inverse dynamics). Here cross products with constant vectors are one
MatMul with a skew matrix, general cross products are MatMuls with permutation matrices, and the
joint rotations are R0 + sin(q) R0 K + (1 - cos(q)) R0 K^2. ``CompactNominal`` stands in for a law's
``NominalModel`` while the bundle is traced; numpy calls go to the original.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from models.dynamics.rne import ChainArrays


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a, dtype=np.float64))


class CompactNominal:
    """inverse_dynamics / gravity with the NominalModel signature; torch path compact, numpy delegated."""

    def __init__(self, original: Any) -> None:
        self.original = original
        chain = ChainArrays.from_robot(original.robot)
        n = chain.n_joints
        self.n = n
        r0 = np.asarray(chain.joint_rotation)
        k = np.asarray(chain.axis_cross)
        # Rodrigues: R = R0 (c (I - a a^T) + a a^T + s K) = R0 + s R0 K + (1 - c) R0 K^2 (K^2 = a a^T - I).
        self.r0 = [_t(r0[i]) for i in range(n)]
        self.r0k = [_t(r0[i] @ k[i]) for i in range(n)]
        self.r0k2 = [_t(r0[i] @ k[i] @ k[i]) for i in range(n)]
        # row-vector convention: for a row v, (w x p) = w @ skew(p)
        p = np.asarray(chain.joint_translation)
        c = np.asarray(chain.com)
        self.skew_p = [_t(_skew(p[i])) for i in range(n)]
        self.skew_c = [_t(_skew(c[i])) for i in range(n)]
        self.c = [_t(c[i]) for i in range(n)]
        self.p = [_t(p[i]) for i in range(n)]
        self.axis = [_t(np.asarray(chain.joint_axis)[i]) for i in range(n)]
        self.axis_col = _t(np.asarray(chain.joint_axis).T)  # (3, N) for tau_i = n_i . z_i
        self.mass = [float(np.asarray(chain.mass)[i]) for i in range(n)]
        self.inertia_t = [_t(np.asarray(chain.inertia)[i].T) for i in range(n)]
        self.gravity_vec = _t(np.asarray(chain.gravity))
        perm1 = np.zeros((3, 3))
        perm2 = np.zeros((3, 3))
        for j in range(3):
            perm1[(j + 1) % 3, j] = 1.0  # (a @ perm1)[j] = a[j+1]
            perm2[(j + 2) % 3, j] = 1.0  # (a @ perm2)[j] = a[j+2]
        self.perm1, self.perm2 = _t(perm1), _t(perm2)

    def _cross(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return (a @ self.perm1) * (b @ self.perm2) - (a @ self.perm2) * (b @ self.perm1)

    def _rotations(self, q: torch.Tensor) -> list[torch.Tensor]:
        s, c = torch.sin(q), 1.0 - torch.cos(q)
        return [self.r0[i] + s[:, i, None, None] * self.r0k[i] + c[:, i, None, None] * self.r0k2[i] for i in range(self.n)]

    def _rne(self, q: torch.Tensor, qd: torch.Tensor | None, qdd: torch.Tensor | None) -> torch.Tensor:
        rot = self._rotations(q)
        batch = q.shape[0]
        accel = (-self.gravity_vec).expand(batch, 3)
        omega = omega_dot = None
        forces, moments = [], []
        for i in range(self.n):
            # a_i = R^T (a + w_dot x p + w x (w x p)); rows: v @ R
            a = accel
            if omega is not None:
                a = a + omega_dot @ self.skew_p[i] + self._cross(omega, omega @ self.skew_p[i])
            accel = (a.unsqueeze(1) @ rot[i]).squeeze(1)
            if qd is not None:
                omega_parent = None if omega is None else (omega.unsqueeze(1) @ rot[i]).squeeze(1)
                axis_rate = qd[:, i : i + 1] * self.axis[i]
                new_omega = axis_rate if omega_parent is None else omega_parent + axis_rate
                od = qdd[:, i : i + 1] * self.axis[i]  # type: ignore[index]
                if omega_dot is not None:
                    od = od + (omega_dot.unsqueeze(1) @ rot[i]).squeeze(1)
                if omega_parent is not None:
                    od = od + self._cross(omega_parent, axis_rate)
                omega, omega_dot = new_omega, od
            if omega is None:
                forces.append(self.mass[i] * accel)
                moments.append(None)
            else:
                acc_com = accel + omega_dot @ self.skew_c[i] + self._cross(omega, omega @ self.skew_c[i])
                forces.append(self.mass[i] * acc_com)
                moments.append(omega_dot @ self.inertia_t[i] + self._cross(omega, omega @ self.inertia_t[i]))
        torques: list[torch.Tensor] = [None] * self.n  # type: ignore[list-item]
        f_next = n_next = None
        for i in range(self.n - 1, -1, -1):
            f_i, n_i = forces[i], self._cross(self.c[i].expand_as(forces[i]), forces[i])
            if moments[i] is not None:
                n_i = n_i + moments[i]
            if f_next is not None:
                r_next = rot[i + 1]
                f_child = (r_next @ f_next.unsqueeze(2)).squeeze(2)
                n_child = (r_next @ n_next.unsqueeze(2)).squeeze(2)
                f_i = f_i + f_child
                n_i = n_i + n_child - f_child @ self.skew_p[i + 1]  # p x f = -(f x p) = -(f @ skew(p))
            torques[i] = n_i @ self.axis[i]
            f_next, n_next = f_i, n_i
        return torch.stack(torques, -1)

    def inverse_dynamics(self, xp: Any, q: Any, qd: Any, qdd: Any) -> Any:
        if xp is np:
            return self.original.inverse_dynamics(xp, q, qd, qdd)
        return self._rne(q, qd, qdd)

    def gravity(self, xp: Any, q: Any) -> Any:
        if xp is np:
            return self.original.gravity(xp, q)
        return self._rne(q, None, None)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.original, name)
