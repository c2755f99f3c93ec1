"""A batch of small box-constrained QPs, min_x  g^T x + 1/2 x^T H x  s.t.  lower <= x <= upper.

Projected Newton with an active set (Bertsekas 1982, simplified for a strictly convex QP):
each iteration fixes the variables that sit on a bound with the gradient pushing outward, takes the
Newton step on the free ones (one batched Cholesky-based solve), projects it onto the box and
backtracks along the projection arc (Armijo). When the free-set Newton step lands inside the box
the KKT conditions hold exactly, so the usual case (no torque bound active) ends after one solve.
Every iterate is feasible, so a caller that stops early still gets a point inside the box.

All arrays carry a leading batch axis K; rows are independent.
"""

from __future__ import annotations

import numpy as np

ARMIJO = 1e-4
STEP_SIZES = 0.5 ** np.arange(12)  # tried all at once, vectorized


def solve_box_qp(
    hessian: np.ndarray, gradient: np.ndarray, lower: np.ndarray, upper: np.ndarray,
    max_iterations: int = 20, tolerance: float = 1e-9,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(x (K, n), converged (K,)): the minimizer of each row's QP inside its box.

    ``hessian`` (K, n, n) symmetric positive definite, ``gradient``, ``lower``, ``upper`` (K, n) with
    lower <= upper. Converged means the projected gradient is below ``tolerance`` (relative to the
    gradient at x = 0) in the max norm.
    """
    k, n = gradient.shape
    scale = np.maximum(np.abs(gradient).max(1), 1e-300)
    # The usual case: the unconstrained minimizer is inside the box, and then it is the answer.
    try:
        free_step = -np.linalg.solve(hessian, gradient[..., None])[..., 0]
        inside = np.all((free_step >= lower) & (free_step <= upper), axis=1)
    except np.linalg.LinAlgError:
        free_step, inside = np.zeros_like(gradient), np.zeros(k, bool)
    if inside.all():
        return free_step, np.ones(k, bool)
    x = np.where(inside[:, None], free_step, np.clip(np.zeros_like(gradient), lower, upper))
    converged = np.zeros(k, bool)
    eye = np.eye(n, dtype=bool)
    for _ in range(max_iterations):
        grad = np.einsum("kij,kj->ki", hessian, x) + gradient
        projected = x - np.clip(x - grad, lower, upper)
        converged = np.abs(projected).max(1) <= tolerance * scale
        if converged.all():
            break
        fixed = ((x <= lower) & (grad > 0)) | ((x >= upper) & (grad < 0))
        free = ~fixed
        # Newton system on the free variables; fixed ones get an identity row/column (step 0).
        both_free = free[:, :, None] & free[:, None, :]
        system = np.where(both_free, hessian, 0.0) + (eye & fixed[:, :, None])
        step = np.linalg.solve(system, np.where(free, -grad, 0.0)[..., None])[..., 0]
        trial = np.clip(x[:, None, :] + STEP_SIZES[None, :, None] * step[:, None, :], lower[:, None], upper[:, None])
        change = trial - x[:, None, :]
        # exact decrease of a quadratic along each trial: g'd + 1/2 d'Hd with g the current gradient
        slope = np.einsum("ksi,ki->ks", change, grad)
        decrease = slope + 0.5 * np.einsum("ksi,ksi->ks", change @ hessian, change)
        sufficient = decrease <= ARMIJO * slope
        first = np.where(sufficient.any(1), sufficient.argmax(1), len(STEP_SIZES) - 1)
        moving = ~converged & sufficient.any(1)
        x = np.where(moving[:, None], trial[np.arange(k), first], x)
        if not moving[~converged].any():  # no row can improve: stationary to round-off
            break
    grad = np.einsum("kij,kj->ki", hessian, x) + gradient
    converged = np.abs(x - np.clip(x - grad, lower, upper)).max(1) <= tolerance * scale
    return x, converged

