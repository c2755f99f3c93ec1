"""HMPC (Sec. III-A, Eq. 17): an MPC layer seeded by any feedback law, solved for a batch of states.

Per state, one call of ``HMPCSolver.solve``:

1. The law's step gives tau_fb (and its next state).
2. Candidates: tau_c = clip(w * tau_fb), w in candidate_scales, held over the preview, plus (when
   warm-starting) last cycle's optimal sequence shifted by one period. Each candidate is rolled out
   through the nominal model and costed; the cheapest is the initial guess.
3. Gauss-Newton on the whole torque sequence U = (tau_1..tau_TN): linearize the rollout (exact
   dynamics derivatives), build the condensed least-squares model H, g of the cost, solve the
   box-constrained QP over the torque bounds (models.hmpc.boxqp), backtrack on the true cost.
   Stop when the QP's predicted decrease is below cost_rtol * J + cost_atol (converged) or the
   iteration budget is spent.
4. Apply tau_1. Rows with non-finite inputs, a non-converged solve (policy ``fallback``) or a
   non-finite result fall back to tau_fb (or the caller's hold torque if tau_fb is not finite);
   every fallback is reported in ``status``. The torque returned is always finite and within bounds.

One algorithm: the array work inside an iteration (cost, condensation, box QP) is done by an
``InnerLoops`` object (``models.hmpc.inner_loops``: numpy, or the compiled numba kernels) chosen
once when the solver is built (``HMPCConfig.kernels``).

The reference preview at k+j comes from the reference's value, rate and acceleration at k
(second-order Taylor, exact for the quadratic part; the error over 5 ms is O((5 ms)^3 q_d''')).
Cost: see HMPCConfig. State bounds are soft (a stiff quadratic penalty) so that a state already
outside them (e.g. just after the impulse) still gives a feasible problem; torque bounds are hard.
"""

from __future__ import annotations

import numpy as np

from models.errors import ModelInputError
from models.feedback.base import FeedbackLaw
from models.hmpc.config import HMPCConfig, per_joint
from models.hmpc.features import feature_jacobian, law_features, torque_changes
from models.hmpc.inner_loops import make_inner_loops
from models.hmpc.prediction import make_predictor
from models.hmpc.result import (
    CONVERGED,
    NONFINITE_INPUT,
    NONFINITE_SOLUTION,
    NOT_CONVERGED,
    HMPCResult,
    Rollout,
    Rows,
)
from models.robots import RobotModel

ARMIJO = 1e-4
LEVENBERG_GROWTH = 1e4  # damping factor after a step the line search rejected
PENALTY_ROUNDS = 4  # semismooth rounds on the state-bound penalty's active set per step


class HMPCSolver:
    """The HMPC optimizer for one law on one nominal robot; ``solve`` takes a batch of states."""

    def __init__(self, law: FeedbackLaw, robot: RobotModel, config: HMPCConfig | None = None) -> None:
        config = HMPCConfig() if config is None else config
        n = robot.n_joints
        if law.n_joints != n:
            raise ModelInputError(f"hmpc: law '{law.name}' has {law.n_joints} joints, robot '{robot.name}' has {n}")
        self.law, self.robot, self.config = law, robot, config
        self.n_joints, self.horizon = n, config.horizon_steps
        self.prediction_step_s = float(
            config.prediction_step_s if config.prediction_step_s is not None else law.period_s
        )
        if not (np.isfinite(self.prediction_step_s) and self.prediction_step_s > 0):
            raise ModelInputError(f"hmpc: prediction_step_s must be > 0, got {self.prediction_step_s}")
        self.predictor = make_predictor(robot, config.backend)
        self.torque_limit_nm = self._limit("torque_limit_nm", config.torque_limit_nm, robot.torque_limit_nm)
        # The position bound is |q - centre| <= limit: centre 0 for a symmetric range, else the range's
        # midpoint (the Panda's elbow lives in [-3.07, -0.07] rad: |q| <= 0 would be infeasible).
        self.position_centre_rad = np.zeros(n)
        position_limit = robot.position_limit_rad
        if config.position_limit_rad is None and robot.position_range_rad is not None:
            lower, upper = robot.position_lower_rad, robot.position_upper_rad
            bounded = np.isfinite(lower) & np.isfinite(upper)
            self.position_centre_rad = np.where(bounded, 0.5 * (lower + upper), 0.0)
            position_limit = np.where(bounded, 0.5 * (upper - lower), np.inf)
        self.position_limit_rad = self._limit("position_limit_rad", config.position_limit_rad, position_limit)
        self.velocity_limit_rad_s = self._limit(
            "velocity_limit_rad_s", config.velocity_limit_rad_s, robot.velocity_limit_rad_s
        )
        self.state_limit = np.concatenate([self.position_limit_rad, self.velocity_limit_rad_s])
        self.scales = np.asarray(config.candidate_scales, float)
        self.temporal = config.temporal_weights
        self.torque_weight = per_joint("torque_weight", config.torque_weight, n)
        self.anchored = config.torque_cost == "anchored"
        # feedforward: W2a on tau - ID(q, qd, qdd_d), the torque beyond the model's feed-forward
        self.feedforward = config.torque_cost == "feedforward"
        # W2 of the optimized cost: on tau (absolute), or on tau - w* tau_fb with c dt^2 / M_ii(0)^2
        # (anchored: equal cost per unit of acceleration deviation on every joint).
        self.anchor_weight: np.ndarray | None = None
        # effort: a torque at the limit costs effort_weight_scale on every joint alike
        self.torque_weight = self.torque_weight + config.effort_weight_scale / self.torque_limit_nm**2
        self.cost_torque_weight = self.torque_weight
        inertia = np.ones(n)
        if self.anchored or self.feedforward or config.rate_weight_scale > 0:
            from models.dynamics import make_dynamics

            inertia = np.diag(np.asarray(make_dynamics(robot, "rne").mass_matrix(np.zeros(n)), float).reshape(n, n))
        if self.feedforward:
            from models.dynamics import make_dynamics

            self._inverse_dynamics = make_dynamics(robot, "pinocchio" if config.backend == "pinocchio" else "rne")
        if self.anchored or self.feedforward:
            self.anchor_weight = config.anchor_weight_scale * self.prediction_step_s**2 / inertia**2
            self.cost_torque_weight = self.anchor_weight
        # smoothness: c dt^2 |M(q)^-1 (tau_j - tau_{j-1})|^2, the change of the acceleration the torque change
        # makes, at the row's own inertia (the full M(q)^-1: a diagonal 1/M_ii^2 let the coupled joints move
        # further from tau_0 than without the term)
        self.smooth = config.rate_weight_scale > 0
        if self.smooth:
            from models.dynamics import make_dynamics

            self._mass = make_dynamics(robot, "pinocchio" if config.backend == "pinocchio" else "rne")
        # the hard rate bound: per control period on tau_1, per prediction step on the later steps
        self.rate_step_nm: np.ndarray | None = None
        if config.torque_rate_limit == "franka":
            from models.effort import max_torque_step_nm

            # a hair inside the bound: the verdict compares tau_k - tau_{k-1} recomputed in floating point
            self.rate_step_nm = max_torque_step_nm(robot.torque_rate_nm_s, law.period_s) * (1.0 - 1e-6)
        # A law that overrides error_features gets its own E (and its state propagated along the
        # preview); the base E = [e, e_dot] does not depend on the law's state, which saves the work.
        self.law_features = type(law).error_features is not FeedbackLaw.error_features
        n_features = 2 * n
        if self.law_features:
            probe = law.error_features(np, law.initial_state(np.zeros((1, n))), *(np.zeros((1, n)),) * 4)
            n_features = int(np.asarray(probe).shape[-1])
            if n_features < 2 * n:
                raise ModelInputError(
                    f"hmpc: law '{law.name}' error features have {n_features} entries, expected >= {2 * n}"
                )
        self.feature_weight = np.concatenate(
            [
                per_joint("position_error_weight", config.position_error_weight, n),
                per_joint("velocity_error_weight", config.velocity_error_weight, n),
                np.full(n_features - 2 * n, config.extra_feature_weight),
            ]
        )
        self.n_features = n_features
        # The array work of each iteration (numpy, or the compiled kernels): chosen here, once.
        self.inner_loops = make_inner_loops(config.kernels)
        self._rho = float(config.state_bound_weight) if config.use_state_bounds else 0.0
        # Constant pieces of the condensed model.
        self._stage_torque_weight = (self.temporal[:, None] * self.cost_torque_weight).reshape(-1)  # (T N,)
        # (D U)_j = U_j - U_{j-1} over the steps; with stage weights w_j: B = D' diag(w) D (T, T), and the
        # Hessian of sum_j w_j (D U)_j' A (D U)_j is kron(B, A) for a row's A = c dt^2 M^-2
        difference = np.eye(self.horizon) - np.eye(self.horizon, k=-1)
        self._rate_steps = difference.T @ (self.temporal[:, None] * difference)
        if self.rate_step_nm is not None:
            ratio = self.prediction_step_s / law.period_s
            self._rate_reach = (1.0 + ratio * np.arange(self.horizon))[:, None] * self.rate_step_nm  # (T, N)
        self._preview_s = self.prediction_step_s * np.arange(1, self.horizon + 1)
        self._stage_feature_weight = np.ascontiguousarray(self.temporal[:, None] * self.feature_weight)  # (T, nE)
        self._torque_box = np.tile(self.torque_limit_nm, self.horizon)
        self._state_box = np.tile(self.state_limit, self.horizon)
        if self.inner_loops.needs_warm_up:
            # Load the compiled kernels now (numba's on-disk cache, ~0.3-0.5 s once per process), not
            # in the first control cycle: one solve at rest exercises every kernel signature.
            zero = np.zeros((1, n))
            self.solve(zero, zero, zero, zero, zero)

    def _limit(self, name: str, override: tuple[float, ...] | None, robot_value: np.ndarray) -> np.ndarray:
        value = per_joint(name, override if override is not None else robot_value, self.n_joints)
        if np.any(np.isnan(value)) or np.any(value <= 0):
            raise ModelInputError(
                f"hmpc {name}: infeasible bounds, every limit must be > 0 (|x| <= limit), got {value.tolist()}"
            )
        return value

    # ------------------------------------------------------------------------------------------
    def reference_preview(self, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q_d, qd_d) at k+1..k+T (B, T, N) from value, rate and acceleration at k."""
        s = self._preview_s[None, :, None]
        return (q_d[:, None] + s * qd_d[:, None] + 0.5 * s * s * qdd_d[:, None], qd_d[:, None] + s * qdd_d[:, None])

    def solve(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        q_d: np.ndarray,
        qd_d: np.ndarray,
        qdd_d: np.ndarray,
        law_state: np.ndarray | None = None,
        warm_start_nm: np.ndarray | None = None,
        hold_torque_nm: np.ndarray | None = None,
        previous_torque_nm: np.ndarray | None = None,
    ) -> HMPCResult:
        """HMPC torques for B independent states (all arrays (B, N); law_state (B, S)).

        ``warm_start_nm`` (B, T, N): last cycle's ``sequence_nm``, shifted here by one period.
        ``hold_torque_nm`` (B, N): what to apply where neither the MPC nor the law gives a finite
        torque (default zero).
        ``previous_torque_nm`` (B, N): tau_0, the torque applied last cycle, for the smoothness term and
        the rate bound (None: neither applies, e.g. the first cycle, or a cold solve of a logged state).
        """
        q, qd, q_d, qd_d, qdd_d = (np.atleast_2d(np.asarray(a, dtype=np.float64)) for a in (q, qd, q_d, qd_d, qdd_d))
        batch, n, horizon = q.shape[0], self.n_joints, self.horizon
        if q.shape[1] != n:
            raise ModelInputError(f"hmpc: states have {q.shape[1]} joints, the robot has {n}")
        if law_state is None:
            law_state = self.law.initial_state(q)
        law_state = np.atleast_2d(np.asarray(law_state, dtype=np.float64))
        with np.errstate(all="ignore"):
            tau_fb, next_state = self.law.step(np, law_state, q, qd, q_d, qd_d, qdd_d)
            tau_fb, next_state = np.asarray(tau_fb, float), np.asarray(next_state, float).reshape(batch, -1)
            ref_q, ref_qd = self.reference_preview(q_d, qd_d, qdd_d)
            finite = (
                np.isfinite(q).all(1)
                & np.isfinite(qd).all(1)
                & np.isfinite(ref_q).all((1, 2))
                & np.isfinite(ref_qd).all((1, 2))
                & np.isfinite(qdd_d).all(1)
                & np.isfinite(tau_fb).all(1)
                & np.isfinite(next_state).all(1)
            )

            status = np.full(batch, NONFINITE_INPUT)
            sequence = np.full((batch, horizon, n), np.nan)
            cost, candidate_cost = np.full(batch, np.nan), np.full(batch, np.nan)
            iterations = np.zeros(batch, int)
            anchor_scale = np.full(batch, np.nan) if self.anchored else None
            valid = np.flatnonzero(finite)
            if valid.size:
                rows = Rows(q[valid], qd[valid], ref_q[valid], ref_qd[valid], qdd_d[valid], next_state[valid])
                if self.feedforward:
                    ff = np.asarray(self._inverse_dynamics.inverse_dynamics(q[valid], qd[valid], qdd_d[valid]), float)
                    rows.anchor = np.ascontiguousarray(np.broadcast_to(ff.reshape(-1, 1, n), (valid.size, horizon, n)))
                previous = None if previous_torque_nm is None else np.asarray(previous_torque_nm, float)
                if previous is not None:
                    previous = np.broadcast_to(previous, (batch, n))[valid]
                    previous = np.where(np.isfinite(previous), previous, tau_fb[valid])
                if self.smooth and previous is not None:
                    rows.previous = np.ascontiguousarray(previous)
                    inverse = np.linalg.inv(np.asarray(self._mass.mass_matrix(q[valid]), float).reshape(-1, n, n))
                    scale = self.config.rate_weight_scale * self.prediction_step_s**2
                    rows.rate_weight = np.ascontiguousarray(scale * np.swapaxes(inverse, 1, 2) @ inverse)
                if self.rate_step_nm is not None and previous is not None:
                    limit = self.torque_limit_nm
                    rows.lower = np.maximum(-limit, previous[:, None] - self._rate_reach)
                    rows.upper = np.minimum(limit, previous[:, None] + self._rate_reach)
                warm = None
                if self.config.warm_start and warm_start_nm is not None:
                    warm = np.asarray(warm_start_nm, float)[valid]
                    warm = np.concatenate([warm[:, 1:], warm[:, -1:]], 1)
                    warm = np.where(np.isfinite(warm), warm, tau_fb[valid, None, :])
                u, c, cc, st, it, w_star = self._optimize(rows, tau_fb[valid], warm)
                sequence[valid], cost[valid], candidate_cost[valid], status[valid], iterations[valid] = u, c, cc, st, it
                if anchor_scale is not None:
                    anchor_scale[valid] = w_star

            first = sequence[:, 0]
            bad_solution = finite & ~np.isfinite(first).all(1)
            status[bad_solution] = NONFINITE_SOLUTION
            use_mpc = (status == CONVERGED) | (
                (status == NOT_CONVERGED) & (self.config.on_budget_exhausted == "best_iterate")
            )
            hold = (
                np.zeros((batch, n))
                if hold_torque_nm is None
                else np.broadcast_to(np.asarray(hold_torque_nm, float), (batch, n))
            )
            # the law's torque where its whole row is finite; otherwise the caller's hold torque
            fb_ok = np.isfinite(tau_fb).all(1, keepdims=True)
            fallback = np.where(fb_ok, tau_fb, np.nan_to_num(hold, nan=0.0, posinf=0.0, neginf=0.0))
            tau = np.where(use_mpc[:, None], first, fallback)
            tau = np.clip(
                np.nan_to_num(tau, nan=0.0, posinf=0.0, neginf=0.0), -self.torque_limit_nm, self.torque_limit_nm
            )
            if self.rate_step_nm is not None and previous_torque_nm is not None:
                # the rate bound holds for the fallback too (a real arm rate-limits every command)
                last = np.broadcast_to(np.asarray(previous_torque_nm, float), (batch, n))
                last = np.where(np.isfinite(last), last, tau)
                tau = np.clip(tau, last - self.rate_step_nm, last + self.rate_step_nm)
            # A law state that went non-finite (NaN measurement) is not carried into the next cycle.
            keep = np.isfinite(next_state).all(1) if next_state.size else np.ones(batch, bool)
            next_state = np.where(keep[:, None], next_state, law_state) if next_state.size else next_state
            next_state = self.law.with_applied_torque(next_state, tau)
        return HMPCResult(
            tau, tau_fb, next_state, sequence, status, ~use_mpc, cost, candidate_cost, iterations, anchor_scale
        )

    # ------------------------------------------------------------------------------------------
    def _optimize(
        self, rows: Rows, tau_fb: np.ndarray, warm: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """Per row: the optimized sequence (K, T, N), its cost, the best paper candidate's cost,
        status, Gauss-Newton iterations, and w* (anchored cost; None for the absolute one)."""
        config, limit = self.config, self.torque_limit_nm
        k, n, horizon = tau_fb.shape[0], self.n_joints, self.horizon
        candidates = np.clip(self.scales[None, :, None] * tau_fb[:, None, :], -limit, limit)  # (K, C, N)
        candidates = np.broadcast_to(candidates[:, :, None, :], (k, len(self.scales), horizon, n))
        if warm is not None:
            candidates = np.concatenate([candidates, np.clip(warm, -limit, limit)[:, None]], 1)
        if rows.lower is not None and rows.upper is not None:  # inside each row's rate box
            candidates = np.clip(candidates, rows.lower[:, None], rows.upper[:, None])
        n_candidates = candidates.shape[1]
        flat = np.ascontiguousarray(candidates.reshape(k * n_candidates, horizon, n))
        w_star = None
        if not self.anchored:
            rolled = self._rollout(rows.repeat(n_candidates), flat)
        else:
            # w* = the cheapest paper candidate under the absolute cost (W2 = torque_weight on tau); then
            # every candidate (and the optimization) is costed with W2a on tau - w* tau_fb.
            rolled = self._rollout(rows.repeat(n_candidates), flat, torque_weight=np.zeros(n))
            base = rolled.cost.reshape(k, n_candidates)
            absolute = base + np.einsum("kctn,n,t->kc", candidates * candidates, self.torque_weight, self.temporal)
            absolute = np.where(np.isfinite(absolute), absolute, np.inf)
            pick = np.argmin(absolute[:, : len(self.scales)], 1)
            w_star = self.scales[pick]
            rows.anchor = np.ascontiguousarray(candidates[np.arange(k), pick])  # (K, T, N)
            deviation = candidates - rows.anchor[:, None]
            rolled.cost = (
                base + np.einsum("kctn,n,t->kc", deviation * deviation, self.cost_torque_weight, self.temporal)
            ).reshape(-1)
        costs = np.where(np.isfinite(rolled.cost), rolled.cost, np.inf).reshape(k, n_candidates)
        candidate_cost = costs[:, : len(self.scales)].min(1)
        best = np.argmin(costs, 1) + np.arange(k) * n_candidates
        u = flat[best].copy()
        state = rolled.take(best)
        status = np.full(k, NOT_CONVERGED)
        iterations = np.zeros(k, int)
        active = np.flatnonzero(np.isfinite(state.cost))
        status[~np.isfinite(state.cost)] = NONFINITE_SOLUTION
        levenberg = np.ones(k)  # damping multiplier: raised after a failed step (Levenberg-Marquardt)

        for _ in range(config.max_iterations):
            if active.size == 0:
                break
            sub_rows, sub_u, sub_state = rows.take(active), u[active], state.take(active)
            step, predicted, exact = self._model_step(sub_rows, sub_u, sub_state, levenberg[active])
            iterations[active] += 1
            # Convergence tests need the model's exact minimizer (QP solved, penalty set settled).
            done = exact & ~(predicted > config.cost_atol + config.cost_rtol * sub_state.cost)
            status[active[done]] = CONVERGED
            pending = np.flatnonzero(~done)
            step = step.reshape(active.size, horizon, n)
            alpha = 1.0
            moved = np.zeros(active.size, bool)
            finished = np.zeros(active.size, bool)
            for _ in range(config.max_line_search_steps + 1):
                if pending.size == 0:
                    break
                trial_u = sub_u[pending] + alpha * step[pending]
                trial = self._rollout(sub_rows.take(pending), trial_u)
                ok = trial.cost <= sub_state.cost[pending] - ARMIJO * alpha * predicted[pending]
                accepted = pending[ok]
                if alpha == 1.0:
                    # A full step whose true decrease matches the model's: the model was exact to
                    # within the tolerance there, so what it leaves to gain is below it too.
                    actual = sub_state.cost[accepted] - trial.cost[ok]
                    agree = exact[accepted] & (
                        np.abs(actual - predicted[accepted]) <= config.cost_atol + config.cost_rtol * trial.cost[ok]
                    )
                    status[active[accepted[agree]]] = CONVERGED
                    finished[accepted[agree]] = True
                u[active[accepted]] = trial_u[ok]
                state.put(active[accepted], trial.take(np.flatnonzero(ok)))
                moved[accepted] = True
                pending, alpha = pending[~ok], 0.5 * alpha
            # A step that could not reduce the cost: retry from the same point with a much more
            # damped (shorter, more gradient-like) step; a good step relaxes the damping again.
            levenberg[active[moved]] = np.maximum(1.0, levenberg[active[moved]] * 0.1)
            levenberg[active[~moved & ~done]] *= LEVENBERG_GROWTH
            active = active[~finished & ~done]
        return u, state.cost, candidate_cost, status, iterations, w_star

    def _rollout(self, rows: Rows, u: np.ndarray, torque_weight: np.ndarray | None = None) -> Rollout:
        """Predicted states, error features and cost of torque sequences u (K, T, N).

        ``torque_weight``: W2 (N,) for this call (default: the optimized cost's), on rows.deviation(u)."""
        dt, predictor = self.prediction_step_s, self.predictor
        weight = self.cost_torque_weight if torque_weight is None else torque_weight
        deviation = rows.deviation(u)
        k, horizon, n = u.shape
        q_path, qd_path = np.empty((k, horizon, n)), np.empty((k, horizon, n))
        q, qd = rows.q0, rows.qd0
        for j in range(horizon):
            qd = qd + dt * predictor.acceleration(q, qd, u[:, j])
            q = q + dt * qd
            q_path[:, j], qd_path[:, j] = q, qd
        features, law_states = self._features(rows, u, q_path, qd_path)
        cost = self.inner_loops.stage_cost(
            features,
            q_path - self.position_centre_rad,  # the bound penalty's coordinates (only it reads q_path)
            qd_path,
            deviation,
            self.feature_weight,
            weight,
            self.temporal,
            self.state_limit,
            self._rho,
        )
        if self.smooth and rows.previous is not None and rows.rate_weight is not None:
            change = torque_changes(rows, u)
            cost = cost + np.einsum("ktn,knm,ktm,t->k", change, rows.rate_weight, change, self.temporal)
        return Rollout(q_path, qd_path, features, law_states, cost)

    def _features(
        self, rows: Rows, u: np.ndarray, q_path: np.ndarray, qd_path: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """E (K, T, nE) along the predicted paths, and the law's state at every step (law-specific
        features; None for the base E = [e, e_dot], which does not depend on it)."""
        if not self.law_features:
            return np.concatenate([rows.ref_q - q_path, rows.ref_qd - qd_path], -1), None
        return law_features(self.law, self.horizon, rows, u, q_path, qd_path)

    def _model_step(
        self, rows: Rows, u: np.ndarray, state: Rollout, levenberg: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The Gauss-Newton step (K, T, N) inside the torque box, the decrease of J it predicts, and
        whether the step is the model's exact minimizer (K,) bool.

        The state-bound penalty is piecewise quadratic in the linearized states x + S d: which
        bounds it acts on is iterated (semismooth Newton: solve, re-evaluate the violated set at
        the predicted states, re-solve) so a step cannot jump far past a bound the model ignored.
        """
        config, horizon, n = self.config, self.horizon, self.n_joints
        k = u.shape[0]
        hessian0, gradient0, sens = self._gauss_newton_model(rows, u, state, levenberg)
        flat_u = u.reshape(k, -1)
        step, predicted, exact = self.inner_loops.model_step(
            hessian0,
            gradient0,
            sens,
            np.concatenate([state.q - self.position_centre_rad, state.qd], -1).reshape(k, -1),
            self._state_box,
            (-self._torque_box if rows.lower is None else rows.lower.reshape(k, -1)) - flat_u,
            (self._torque_box if rows.upper is None else rows.upper.reshape(k, -1)) - flat_u,
            self._rho,
            PENALTY_ROUNDS,
            config.max_qp_iterations,
            config.qp_tolerance,
        )
        return step.reshape(k, horizon, n), predicted, exact

    def _gauss_newton_model(
        self, rows: Rows, u: np.ndarray, state: Rollout, levenberg: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Condensed model of J / 2 without the bound penalty: H (K, TN, TN), g (K, TN), and the
        state sensitivities S = dx/dU (K, T 2N, TN)."""
        dt, n, horizon = self.prediction_step_s, self.n_joints, self.horizon
        k = u.shape[0]
        q_prev = np.concatenate([rows.q0[:, None], state.q[:, :-1]], 1).reshape(-1, n)
        qd_prev = np.concatenate([rows.qd0[:, None], state.qd[:, :-1]], 1).reshape(-1, n)
        _, d_q, d_qd, d_tau = self.predictor.acceleration_derivatives(q_prev, qd_prev, u.reshape(-1, n))
        d_q, d_qd, d_tau = (a.reshape(k, horizon, n, n) for a in (d_q, d_qd, d_tau))
        sens = self.inner_loops.sensitivities(d_q, d_qd, d_tau, dt)  # (K, T 2N, TN)
        if self.law_features:  # E(U + d) = E + (dE/dx) S d
            jac = feature_jacobian(self.law, rows, state)  # (K, T, nE, 2N)
            feature_sens = (jac @ sens.reshape(k, horizon, 2 * n, -1)).reshape(k, -1, horizon * n)
            residual = state.features
        else:  # E = ref - x: E(U + d) = E - S d, i.e. the residual -E with sensitivity S
            feature_sens, residual = sens, -state.features
        hessian, gradient = self.inner_loops.normal_equations(
            feature_sens,
            self._stage_feature_weight,
            residual,
            rows.deviation(u).reshape(k, -1),
            self._stage_torque_weight,
            float(self.config.damping),
            levenberg,
        )
        if self.smooth and rows.previous is not None and rows.rate_weight is not None:
            # 1/2 (D U - d0)' W (D U - d0): Hessian D' W D, gradient D' W (D U - d0), (D' y)_j = y_j - y_{j+1}
            weighted = np.einsum("knm,ktm,t->ktn", rows.rate_weight, torque_changes(rows, u), self.temporal)
            shifted = np.concatenate([weighted[:, 1:], np.zeros_like(weighted[:, :1])], 1)
            blocks = np.einsum("ab,kij->kaibj", self._rate_steps, rows.rate_weight).reshape(k, horizon * n, horizon * n)
            hessian = hessian + blocks
            gradient = gradient + (weighted - shifted).reshape(k, -1)
        return hessian, gradient, sens
