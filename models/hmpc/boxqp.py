"""A batch of small box-constrained QPs, min_x  g^T x + 1/2 x^T H x  s.t.  lower <= x <= upper.

Two active-set methods, both written here and vectorized over the batch (rows are independent):

1. Primal-dual active set (Hintermueller, Ito, Kunisch 2002): guess which bounds are active from
   the last iterate and its multipliers, solve the equality-constrained QP on the free variables
   (one batched linear solve), repeat until the active set repeats; it then satisfies the KKT
   conditions exactly. Starting from the unconstrained minimizer it usually needs 1-3 solves, and
   the common case (no torque bound active) ends after the first.
2. A primal active-set method (Nocedal & Wright, Alg. 16.3, specialized to bounds) for the rows
   where the primal-dual iteration cycles: feasible iterates, the objective never increases, and
   it ends after finitely many working-set changes; a caller that stops early still gets a point
   inside the box that is no worse than the start.
"""

from __future__ import annotations

import numpy as np


def _objective(hessian: np.ndarray, gradient: np.ndarray, x: np.ndarray) -> np.ndarray:
    value: np.ndarray = np.einsum("ki,ki->k", gradient + 0.5 * (hessian @ x[..., None])[..., 0], x)
    return value


def solve_box_qp(
    hessian: np.ndarray,
    gradient: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    max_iterations: int = 20,
    tolerance: float = 1e-9,
    guess: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(x (K, n), converged (K,)): the minimizer of each row's QP inside its box.

    ``hessian`` (K, n, n) symmetric positive definite, ``gradient``, ``lower``, ``upper`` (K, n) with
    lower <= upper. Converged: the KKT conditions hold (projected gradient below ``tolerance``
    relative to the gradient at x = 0, max norm). ``max_iterations`` bounds each method's solves.
    ``guess`` (K, n): the bounds a row's guess sits on are its first active set (a warm start:
    the minimizer is unique, only the iteration count changes); rows whose guess is on no bound
    start from the unconstrained minimizer.
    """
    k, n = gradient.shape
    scale = np.maximum(np.abs(gradient).max(1), 1e-300)
    with np.errstate(all="ignore"):
        x = -np.linalg.solve(hessian, gradient[..., None])[..., 0]
    preset_upper: np.ndarray
    preset_lower: np.ndarray
    if guess is None:
        preset_upper = preset_lower = np.zeros((k, n), bool)
    else:
        preset_upper = guess >= upper - 1e-12 * (1 + np.abs(upper))
        preset_lower = (guess <= lower + 1e-12 * (1 + np.abs(lower))) & ~preset_upper
    preset = (preset_upper | preset_lower).any(1)
    inside = ~preset & np.all((x >= lower) & (x <= upper), axis=1)
    if inside.all():
        return x, np.ones(k, bool)

    # 1. primal-dual active set on the rows whose unconstrained minimizer leaves the box
    converged = inside.copy()
    todo = np.flatnonzero(~inside)
    diag_scale = np.einsum("kii->ki", hessian)  # makes multiplier and bound distance comparable
    xt, mult = x[todo], np.zeros((todo.size, n))
    at_upper_prev = at_lower_prev = None
    first_upper, first_lower, first = preset_upper[todo], preset_lower[todo], preset[todo][:, None]
    for _ in range(max_iterations):
        h, g, lo, hi, c = hessian[todo], gradient[todo], lower[todo], upper[todo], diag_scale[todo]
        at_upper = mult + c * (xt - hi) > 0
        at_lower = (mult + c * (xt - lo) < 0) & ~at_upper
        if at_upper_prev is None:  # the warm rows' first active set is their guess's
            at_upper = np.where(first, first_upper, at_upper)
            at_lower = np.where(first, first_lower, at_lower)
        if at_upper_prev is not None:
            same = np.all(at_upper == at_upper_prev, 1) & np.all(at_lower == at_lower_prev, 1)
            feasible = np.all((xt >= lo - 1e-12 * (1 + np.abs(lo))) & (xt <= hi + 1e-12 * (1 + np.abs(hi))), 1)
            finished = same & feasible
            x[todo[finished]] = np.clip(xt[finished], lo[finished], hi[finished])
            converged[todo[finished]] = True
            keep = ~finished
            todo, xt, mult, at_upper, at_lower = todo[keep], xt[keep], mult[keep], at_upper[keep], at_lower[keep]
            h, g, lo, hi = h[keep], g[keep], lo[keep], hi[keep]
            if todo.size == 0:
                break
        active = at_upper | at_lower
        x_active = np.where(at_upper, hi, np.where(at_lower, lo, 0.0))
        free = ~active
        system = np.where(free[:, :, None] & free[:, None, :], h, 0.0) + np.eye(n) * active[:, :, None]
        rhs = np.where(free, -g - (h @ x_active[..., None])[..., 0], x_active)
        with np.errstate(all="ignore"):
            xt = np.linalg.solve(system, rhs[..., None])[..., 0]
        mult = np.where(active, -((h @ xt[..., None])[..., 0] + g), 0.0)
        at_upper_prev, at_lower_prev = at_upper, at_lower
    if todo.size == 0:
        return x, converged

    # 2. primal active set for the rows left (PDAS can cycle when H is far from an M-matrix):
    #    feasible iterates; each step solves on the free set, walks toward that solution until a
    #    bound blocks (the blocking variable joins the working set) or, when it gets there,
    #    releases the bound with the most wrong-signed multiplier. Finite, monotone.
    lo_all, hi_all = lower[todo], upper[todo]
    start_a = np.clip(np.nan_to_num(xt), lo_all, hi_all)
    start_b = np.clip(np.zeros_like(start_a), lo_all, hi_all)
    better = _objective(hessian[todo], gradient[todo], start_a) <= _objective(hessian[todo], gradient[todo], start_b)
    x[todo] = np.where(better[:, None], start_a, start_b)
    xt = x[todo]
    at_lo, at_hi = xt <= lo_all, xt >= hi_all
    for _ in range(4 * max_iterations):
        h, g, lo, hi = hessian[todo], gradient[todo], lower[todo], upper[todo]
        working = at_lo | at_hi
        free = ~working
        system = np.where(free[:, :, None] & free[:, None, :], h, 0.0) + np.eye(n) * working[:, :, None]
        rhs = np.where(free, -g - (h @ np.where(working, xt, 0.0)[..., None])[..., 0], xt)
        target = np.linalg.solve(system, rhs[..., None])[..., 0]
        direction = target - xt
        # ratio test: the largest fraction of the way to the target that stays inside the box
        with np.errstate(divide="ignore", invalid="ignore"):
            room = np.where(
                direction > 0, (hi - xt) / direction, np.where(direction < 0, (lo - xt) / direction, np.inf)
            )
        room = np.where(free, np.maximum(room, 0.0), np.inf)
        blocking = np.argmin(room, 1)
        fraction = np.minimum(room[np.arange(todo.size), blocking], 1.0)
        xt = np.clip(xt + fraction[:, None] * direction, lo, hi)
        blocked = fraction < 1.0
        rows = np.flatnonzero(blocked)
        hit_hi = direction[rows, blocking[rows]] > 0
        at_hi[rows[hit_hi], blocking[rows[hit_hi]]] = True
        at_lo[rows[~hit_hi], blocking[rows[~hit_hi]]] = True
        # at the free-set optimum: multipliers of the working bounds (>= 0 when correct)
        grad = (h @ xt[..., None])[..., 0] + g
        wrong = np.where(at_lo, -grad, 0.0) + np.where(at_hi, grad, 0.0)  # > 0: the bound holds x back wrongly
        wrong = np.where(blocked[:, None], 0.0, wrong)
        worst = np.argmax(wrong, 1)
        release = ~blocked & (wrong[np.arange(todo.size), worst] > tolerance * scale[todo])
        rows = np.flatnonzero(release)
        at_lo[rows, worst[rows]] = False
        at_hi[rows, worst[rows]] = False
        finished = ~blocked & ~release
        x[todo] = xt
        converged[todo[finished]] = True
        keep = ~finished
        todo, xt, at_lo, at_hi = todo[keep], xt[keep], at_lo[keep], at_hi[keep]
        if todo.size == 0:
            break
    grad = np.einsum("kij,kj->ki", hessian, x) + gradient
    converged = np.abs(x - np.clip(x - grad, lower, upper)).max(1) <= tolerance * scale
    return x, converged
