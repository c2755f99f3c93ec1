"""Compiled (numba) kernels for the HMPC's inner loops, row by row.

``models.hmpc.inner_loops.NumbaInnerLoops`` calls them; ``NumpyInnerLoops`` beside it runs the
same algorithms vectorized in numpy. The solver spends its time, per Gauss-Newton iteration, in
three places outside pinocchio: condensing the linearized rollout into S, H, g
(`sensitivities`, `normal_equations`); the box QP over the torque box, with the state-bound
penalty's semismooth rounds around it (`model_step`); and, for batch labeling, hundreds of those
per call. In numpy every one of them is tens of small array operations, each with microseconds of
overhead, and the active-set loops run until the slowest row finishes. Here each row is solved on
its own in compiled code (no per-operation overhead, no waiting on other rows), with the same
algorithms as ``models.hmpc.boxqp`` and ``NumpyInnerLoops``:

- box QP: primal-dual active set (Hintermueller-Ito-Kunisch), and where it cycles the primal
  active-set method (feasible, monotone, finite); the equality-constrained solves on the free set
  by Cholesky (H is symmetric positive definite: Gauss-Newton plus the Levenberg floor).
- model step: the state-bound penalty's active set iterated (<= ``rounds`` QP solves).
- sensitivities: S = dx/dU by the block recursion S_j = Phi_j S_{j-1} + [.. Gamma_j], using that S
  is block lower triangular; normal equations: H = F' W F + diag(W2) + damping, g = F' W r + W2 U.

The kernels compile on first use and are cached on disk (``cache=True``), so a fresh process pays
the compile once per machine, not per call. Importing this module needs numba.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar, cast

import numba
import numpy as np
import numpy.typing as npt

# This module is imported lazily, by the first solver that uses it (numba's import takes ~0.5 s).

Floats = npt.NDArray[np.float64]
Bools = npt.NDArray[np.bool_]
Kernel = TypeVar("Kernel", bound=Callable[..., Any])


def _jit(fn: Kernel) -> Kernel:
    """Compiled with numba (the annotations are for readers and mypy; numba types by the call)."""
    return cast(Kernel, numba.njit(cache=True, fastmath={"reassoc", "contract"}, nogil=True)(fn))


@_jit
def _solve_free(h: Floats, rhs: Floats, free: Bools, out: Floats, work: Floats) -> bool:
    """out[free] = H[free, free]^-1 rhs[free] by Cholesky (work: (m, m) scratch); False if not PD."""
    m = h.shape[0]
    index = np.empty(m, np.int64)
    nf = 0
    for i in range(m):
        if free[i]:
            index[nf] = i
            nf += 1
    for a in range(nf):
        for b in range(a + 1):
            s = h[index[a], index[b]]
            for c in range(b):
                s -= work[a, c] * work[b, c]
            if a == b:
                if not s > 0.0:
                    return False
                work[a, a] = np.sqrt(s)
            else:
                work[a, b] = s / work[b, b]
    y = np.empty(nf)
    for a in range(nf):
        s = rhs[index[a]]
        for c in range(a):
            s -= work[a, c] * y[c]
        y[a] = s / work[a, a]
    for a in range(nf - 1, -1, -1):
        s = y[a]
        for c in range(a + 1, nf):
            s -= work[c, a] * y[c]
        y[a] = s / work[a, a]
    for a in range(nf):
        out[index[a]] = y[a]
    return True


@_jit
def _solve_free_set(h: Floats, g: Floats, free: Bools, fixed: Floats, out: Floats, rhs: Floats, work: Floats) -> bool:
    """out[free] = argmin g'x + 1/2 x'Hx over the free variables, the others held at fixed[~free]
    (rhs: (m,) scratch); False if H[free, free] is not positive definite. ``out`` may be ``fixed``."""
    m = g.shape[0]
    for i in range(m):
        if free[i]:
            s = -g[i]
            for j in range(m):
                if not free[j]:
                    s -= h[i, j] * fixed[j]
            rhs[i] = s
    return _solve_free(h, rhs, free, out, work)


@_jit
def _hx_plus_g(h: Floats, x: Floats, g: Floats, out: Floats) -> None:
    m = x.shape[0]
    for i in range(m):
        s = g[i]
        for j in range(m):
            s += h[i, j] * x[j]
        out[i] = s


@_jit
def _objective(h: Floats, g: Floats, x: Floats) -> float:
    m = x.shape[0]
    total = 0.0
    for i in range(m):
        s = 0.0
        for j in range(m):
            s += h[i, j] * x[j]
        total += (g[i] + 0.5 * s) * x[i]
    return total


@_jit
def box_qp_row(
    h: Floats,
    g: Floats,
    lo: Floats,
    hi: Floats,
    max_iterations: int,
    tolerance: float,
    x: Floats,
    work: Floats,
    warm: bool = False,
) -> bool:
    """One box QP, min g'x + 1/2 x'Hx, lo <= x <= hi, into x; returns converged (KKT).

    ``warm``: x holds a guess whose bounds at which it sits are the first active set of the
    primal-dual iteration (the last penalty round's solution; or x = 0 where the torque already
    sits on its limit). The minimizer is unique (H positive definite), so a guess changes only how
    many iterations it takes: ~2 instead of ~15-20 on a penalty round's re-solve. Without a guess,
    or one on no bound, the iteration starts from the unconstrained minimizer, as in boxqp.py.
    """
    m = g.shape[0]
    scale = 1e-300
    for i in range(m):
        scale = max(scale, abs(g[i]))
    free = np.ones(m, np.bool_)
    rhs = np.empty(m)
    mult = np.zeros(m)
    at_upper = np.zeros(m, np.bool_)
    at_lower = np.zeros(m, np.bool_)
    preset = False
    if warm:
        for i in range(m):
            at_upper[i] = x[i] >= hi[i] - 1e-12 * (1 + abs(hi[i]))
            at_lower[i] = (x[i] <= lo[i] + 1e-12 * (1 + abs(lo[i]))) and not at_upper[i]
            preset = preset or at_upper[i] or at_lower[i]
    if not preset:
        ok = _solve_free_set(h, g, free, x, x, rhs, work)  # every variable free: the unconstrained minimizer
        inside = ok
        if ok:
            for i in range(m):
                if not (x[i] >= lo[i] and x[i] <= hi[i]):
                    inside = False
                    break
        if inside:
            return True
        if not ok:
            for i in range(m):
                x[i] = 0.0
    # 1. primal-dual active set
    prev_upper = np.zeros(m, np.bool_)
    prev_lower = np.zeros(m, np.bool_)
    grad = np.empty(m)
    for it in range(max_iterations):
        if not (preset and it == 0):
            for i in range(m):
                c = h[i, i]
                at_upper[i] = mult[i] + c * (x[i] - hi[i]) > 0
                at_lower[i] = (mult[i] + c * (x[i] - lo[i]) < 0) and not at_upper[i]
        if it > 0:
            same = True
            feasible = True
            for i in range(m):
                if at_upper[i] != prev_upper[i] or at_lower[i] != prev_lower[i]:
                    same = False
                if not (x[i] >= lo[i] - 1e-12 * (1 + abs(lo[i])) and x[i] <= hi[i] + 1e-12 * (1 + abs(hi[i]))):
                    feasible = False
            if same and feasible:
                for i in range(m):
                    x[i] = min(max(x[i], lo[i]), hi[i])
                return True
        for i in range(m):
            free[i] = not (at_upper[i] or at_lower[i])
            x[i] = hi[i] if at_upper[i] else (lo[i] if at_lower[i] else 0.0)
        if not _solve_free_set(h, g, free, x, x, rhs, work):
            break
        _hx_plus_g(h, x, g, grad)
        for i in range(m):
            mult[i] = 0.0 if free[i] else -grad[i]
            prev_upper[i] = at_upper[i]
            prev_lower[i] = at_lower[i]
    # 2. primal active set from the better of the clipped PDAS iterate and the clipped origin
    start_a = np.empty(m)
    start_b = np.empty(m)
    for i in range(m):
        v = x[i] if np.isfinite(x[i]) else 0.0
        start_a[i] = min(max(v, lo[i]), hi[i])
        start_b[i] = min(max(0.0, lo[i]), hi[i])
    if _objective(h, g, start_a) <= _objective(h, g, start_b):
        x[:] = start_a
    else:
        x[:] = start_b
    at_lo = np.empty(m, np.bool_)
    at_hi = np.empty(m, np.bool_)
    for i in range(m):
        at_lo[i] = x[i] <= lo[i]
        at_hi[i] = x[i] >= hi[i]
    target = np.empty(m)
    for _ in range(4 * max_iterations):
        for i in range(m):
            free[i] = not (at_lo[i] or at_hi[i])
            if not free[i]:
                target[i] = x[i]
        if not _solve_free_set(h, g, free, x, target, rhs, work):
            break
        best_room = np.inf
        blocking = 0
        for i in range(m):
            if free[i]:
                d = target[i] - x[i]
                if d > 0:
                    room = max((hi[i] - x[i]) / d, 0.0)
                elif d < 0:
                    room = max((lo[i] - x[i]) / d, 0.0)
                else:
                    room = np.inf
                if room < best_room:
                    best_room, blocking = room, i
        fraction = min(best_room, 1.0)
        direction_blocking = target[blocking] - x[blocking]
        for i in range(m):
            x[i] = min(max(x[i] + fraction * (target[i] - x[i]), lo[i]), hi[i])
        if fraction < 1.0:
            if direction_blocking > 0:
                at_hi[blocking] = True
            else:
                at_lo[blocking] = True
            continue
        _hx_plus_g(h, x, g, grad)
        worst, worst_value = 0, -np.inf
        for i in range(m):
            wrong = (-grad[i] if at_lo[i] else 0.0) + (grad[i] if at_hi[i] else 0.0)
            if wrong > worst_value:
                worst, worst_value = i, wrong
        if worst_value > tolerance * scale:
            at_lo[worst] = False
            at_hi[worst] = False
        else:
            break
    _hx_plus_g(h, x, g, grad)
    for i in range(m):
        if not abs(x[i] - min(max(x[i] - grad[i], lo[i]), hi[i])) <= tolerance * scale:
            return False
    return True


@_jit
def box_qp(
    hessian: Floats, gradient: Floats, lower: Floats, upper: Floats, max_iterations: int, tolerance: float
) -> tuple[Floats, Bools]:
    """``models.hmpc.boxqp.solve_box_qp`` row by row: (x (K, n), converged (K,))."""
    k, m = gradient.shape
    x = np.zeros((k, m))
    converged = np.zeros(k, np.bool_)
    work = np.empty((m, m))
    for r in range(k):
        converged[r] = box_qp_row(hessian[r], gradient[r], lower[r], upper[r], max_iterations, tolerance, x[r], work)
    return x, converged


@_jit
def _penalty(x: Floats, limit: Floats, rho: float) -> float:
    total = 0.0
    for i in range(x.shape[0]):
        v = x[i] - min(max(x[i], -limit[i]), limit[i])
        total += v * v
    return 0.5 * rho * total


@_jit
def _side(value: float, limit: float) -> float:
    """Which bound of |value| <= limit is violated: +1 upper, -1 lower, 0 none."""
    return (1.0 if value > 0 else -1.0) if abs(value) > limit else 0.0


@_jit
def model_step(
    hessian0: Floats,
    gradient0: Floats,
    sens: Floats,
    x: Floats,
    limit: Floats,
    lower: Floats,
    upper: Floats,
    rho: float,
    rounds: int,
    max_qp_iterations: int,
    qp_tolerance: float,
) -> tuple[Floats, Floats, Bools]:
    """``NumpyInnerLoops.model_step`` row by row: (step (K, M), predicted decrease of J (K,),
    exact (K,)). The penalty 1/2 rho |x_A + S_A d - b_A|^2 acts on the violated set A,
    re-evaluated at the predicted states up to ``rounds`` times."""
    k, m = gradient0.shape
    nx = x.shape[1]
    step = np.zeros((k, m))
    predicted = np.zeros(k)
    exact = np.zeros(k, np.bool_)
    work = np.empty((m, m))
    hessian = np.empty((m, m))
    gradient = np.empty(m)
    side = np.empty(nx)
    y = np.empty(nx)
    for r in range(k):
        for a in range(nx):
            side[a] = _side(x[r, a], limit[a])
        settled = rho == 0.0
        qp_converged = False
        # step[r] = 0: the first QP's guess is the torques already on their limits (lower or
        # upper = 0), i.e. last Gauss-Newton step's active set; later rounds start from the last.
        for _ in range(rounds if rho > 0 else 1):
            hessian[:, :] = hessian0[r]
            gradient[:] = gradient0[r]
            if rho > 0:
                for a in range(nx):
                    if side[a] != 0.0:
                        s = sens[r, a]
                        b = x[r, a] - side[a] * limit[a]
                        for i in range(m):
                            if s[i] != 0.0:
                                gradient[i] += rho * s[i] * b
                                for j in range(m):
                                    hessian[i, j] += rho * s[i] * s[j]
            qp_converged = box_qp_row(
                hessian, gradient, lower[r], upper[r], max_qp_iterations, qp_tolerance, step[r], work, True
            )
            if rho == 0:
                break
            same = True
            for a in range(nx):  # y = x + S d: the predicted states, and the bounds they violate
                v = x[r, a]
                for i in range(m):
                    v += sens[r, a, i] * step[r, i]
                y[a] = v
                new = _side(v, limit[a])
                if new != side[a]:
                    same = False
                side[a] = new
            if same:
                settled = True
                break
        change = _objective(hessian0[r], gradient0[r], step[r])
        if rho > 0:  # y holds the predicted states of the final step
            change += _penalty(y, limit, rho) - _penalty(x[r], limit, rho)
        predicted[r] = -2.0 * change  # the model is of J / 2
        exact[r] = settled and qp_converged
    return step, predicted, exact


@_jit
def sensitivities(d_q: Floats, d_qd: Floats, d_tau: Floats, dt: float) -> Floats:
    """S = dx/dU (K, T 2N, TN) of the linearized semi-implicit Euler rollout, from the per-step
    dynamics derivatives (K, T, N, N); block lower triangular (x_j depends on u_1..u_j only)."""
    k, horizon, n = d_q.shape[0], d_q.shape[1], d_q.shape[2]
    m, nx = horizon * n, horizon * 2 * n
    sens = np.zeros((k, nx, m))
    phi = np.empty((2 * n, 2 * n))
    for r in range(k):
        s = sens[r]
        for j in range(horizon):
            row0 = j * 2 * n
            # x+ = Phi x + Gamma u: Phi = [[I + dt^2 Aq, dt (I + dt Aqd)], [dt Aq, I + dt Aqd]]
            if j > 0:
                for a in range(n):
                    for b in range(n):
                        eye = 1.0 if a == b else 0.0
                        vel = eye + dt * d_qd[r, j, a, b]
                        phi[a, b] = eye + dt * dt * d_q[r, j, a, b]
                        phi[a, n + b] = dt * vel
                        phi[n + a, b] = dt * d_q[r, j, a, b]
                        phi[n + a, n + b] = vel
                prev0 = row0 - 2 * n
                for a in range(2 * n):
                    for c in range(j * n):
                        v = 0.0
                        for b in range(2 * n):
                            v += phi[a, b] * s[prev0 + b, c]
                        s[row0 + a, c] = v
            for a in range(n):
                for b in range(n):
                    s[row0 + a, j * n + b] = dt * dt * d_tau[r, j, a, b]
                    s[row0 + n + a, j * n + b] = dt * d_tau[r, j, a, b]
    return sens


@_jit
def normal_equations(
    feature_sens: Floats,
    weights: Floats,
    residual: Floats,
    deviation: Floats,
    torque_weight: Floats,
    damping: float,
    levenberg: Floats,
) -> tuple[Floats, Floats]:
    """H (K, TN, TN), g (K, TN) of the Gauss-Newton model of J / 2 (without the bound penalty):
    1/2 sum w (r + F d)^2 + 1/2 sum W2 (dev + d)^2, F = dE/dU (K, T nE, TN) block lower triangular,
    weights (T, nE), residual r (K, T, nE), deviation (K, TN); plus the Levenberg damping."""
    k, horizon, n_features = residual.shape
    m = feature_sens.shape[2]
    n = m // horizon
    hessian = np.zeros((k, m, m))
    gradient = np.zeros((k, m))
    for r in range(k):
        f = feature_sens[r]
        h = hessian[r]
        g = gradient[r]
        for j in range(horizon):
            cols = (j + 1) * n  # stage j depends on u_1..u_j only
            for a in range(n_features):
                row = j * n_features + a
                w = weights[j, a]
                res = w * residual[r, j, a]
                for c in range(cols):
                    fc = f[row, c]
                    if fc != 0.0:
                        g[c] += fc * res
                        wfc = w * fc
                        for d in range(c + 1):
                            h[c, d] += wfc * f[row, d]
        total = 0.0
        for c in range(m):
            for d in range(c):
                h[d, c] = h[c, d]
            h[c, c] += torque_weight[c]
            g[c] += torque_weight[c] * deviation[r, c]
            total += h[c, c]
        extra = damping * levenberg[r] * (total / m) + 1e-300
        for c in range(m):
            h[c, c] += extra
    return hessian, gradient


@_jit
def stage_cost(
    features: Floats,
    q_path: Floats,
    qd_path: Floats,
    deviation: Floats,
    feature_weight: Floats,
    torque_weight: Floats,
    temporal: Floats,
    state_limit: Floats,
    rho: float,
) -> Floats:
    """J (K,) of predicted paths (K, T, N) with error features E (K, T, nE), E[..., :2N] = [e, e_dot]:
    sum_j w_j [E_j' W1 E_j + u_j' W2 u_j] + rho |x - clip(x, -limit, limit)|^2."""
    k, horizon, n = q_path.shape
    n_features = features.shape[2]
    cost = np.empty(k)
    for r in range(k):
        total = 0.0
        violation = 0.0
        for j in range(horizon):
            stage = 0.0
            for i in range(n):
                e = features[r, j, i]
                ed = features[r, j, n + i]
                stage += feature_weight[i] * (e * e) + feature_weight[n + i] * (ed * ed)
                stage += torque_weight[i] * (deviation[r, j, i] * deviation[r, j, i])
                if rho > 0:
                    v = q_path[r, j, i] - min(max(q_path[r, j, i], -state_limit[i]), state_limit[i])
                    vd = qd_path[r, j, i] - min(max(qd_path[r, j, i], -state_limit[n + i]), state_limit[n + i])
                    violation += v * v + vd * vd
            for a in range(2 * n, n_features):  # a law's own features beyond [e, e_dot]
                stage += feature_weight[a] * (features[r, j, a] * features[r, j, a])
            total += temporal[j] * stage
        cost[r] = total + rho * violation
    return cost
