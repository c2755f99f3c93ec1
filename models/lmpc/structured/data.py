"""On-policy training data of the structured LMPC: the expert's (HMPC) closed-loop rollouts, optionally
excited (DART) and perturbed, DAgger rollouts relabeled by cold HMPC solves, their features and their
cache in the work directory."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from models.errors import ModelInputError
from models.executors import Executor
from models.feedback import make_law
from models.feedback.base import FeedbackLaw
from models.lmpc.structured.config import StructuredConfig, jsonable_config
from models.robots import RobotModel, load_robot
from models.sim import ControllerStack, SimConfig, batch_key, simulate


def _logged_rollouts(
    robot: RobotModel,
    controllers: list[Any],
    laws: list[FeedbackLaw],
    conditions: list[Any],
    sim: SimConfig,
    stride: int,
    excite: tuple[np.ndarray, np.ndarray] | None = None,
    hold: int = 1,
    seed: int = 0,
    log_previous: bool = False,
    realism: Any = None,
) -> list[dict[str, np.ndarray]]:
    """Run controllers side by side on ``conditions`` (one simulator batch: they share duration, disturbance
    and mismatch) in the world ``realism`` (None: ideal); per controller the logged states and torques."""
    from models.lmpc.expert_rollouts import StateLogger

    steps = int(round(conditions[0].duration_s / sim.period_s))
    loggers = []
    for c, law in zip(controllers, laws, strict=True):  # each controller runs (the export of) its law
        loggers.append(StateLogger(c, len(conditions), steps, stride, law.n_joints, law.state_size, True, log_previous))
    runners: list[Any] = loggers
    if excite is not None:
        runners = [_Excited(lg, excite[0], hold, excite[1], seed + 1000 * k) for k, lg in enumerate(loggers)]
    traj = simulate(
        robot,
        ControllerStack(runners, [len(conditions)] * len(runners)),
        [x for _ in loggers for x in conditions],
        sim,
        realism=realism,
    )
    out = []
    for k, logger in enumerate(loggers):
        rows = logger.log["t_s"].size
        part = slice(k * len(conditions), (k + 1) * len(conditions))
        ok = np.repeat(traj.finite[part] & traj.within_limits[part], rows)
        data = {
            "t_s": np.tile(logger.log["t_s"], len(conditions)),
            **{key: v.reshape(len(conditions) * rows, -1) for key, v in logger.log.items() if key != "t_s"},
        }
        out.append({key: v[ok] for key, v in data.items()})
    return out


class _Excited:
    """Adds held, seeded noise (per row of the batch) to a controller's torque; the label is the clean one."""

    def __init__(self, inner: Any, amplitude_nm: np.ndarray, hold: int, rows_on: np.ndarray, seed: int) -> None:
        self.inner, self.amplitude, self.hold, self.rows_on = inner, amplitude_nm, hold, rows_on
        self.name = inner.name + "-excited"
        self.cycle_times_s: list[float] = []
        self.last_tau_fb: np.ndarray | None = None
        self.seed = seed

    def reset(self, q0: np.ndarray) -> None:
        self.inner.reset(q0)
        self.k, self.rng, self.noise = 0, np.random.default_rng(self.seed), np.zeros_like(np.atleast_2d(q0))

    def __call__(
        self, t_s: float, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray
    ) -> np.ndarray:
        tau = self.inner(t_s, q, qd, q_d, qd_d, qdd_d)
        self.last_tau_fb = self.inner.last_tau_fb
        if self.k % self.hold == 0:
            self.noise = self.rng.standard_normal(q.shape) * self.amplitude * self.rows_on[:, None]
        self.k += 1
        return tau + self.noise


def collect(
    config: StructuredConfig,
    conditions: list[Any],
    law_names: tuple[str, ...] | None = None,
    policy_dir: Path | None = None,
    executor: Executor | None = None,
    draw_seed: int | None = None,
) -> dict[str, dict[str, np.ndarray]]:
    """Per law: logged states with the label ``tau_star``.

    ``config.train_realism``: the rollouts run in ``config.realism_draws`` seeded worlds drawn around that
    profile (domain randomization, models.lmpc.structured.randomization; ``draw_seed``, default the
    training seed, seeds the draws); None: the ideal world.

    Expert (policy_dir None): the HMPC's own closed loop, label = the torque it applied (target
    "hmpc") or the FB closed loop labeled with tau_fb (target "law"). DAgger (policy_dir given):
    the LMPC of ``policy_dir`` runs, the visited states are labeled by cold HMPC solves.
    """
    from models.hmpc import make_hmpc_controller
    from models.sim import FeedbackController

    robot = load_robot(config.robot)
    sim = SimConfig(period_s=config.period_s, substeps=config.substeps)
    laws = law_names or config.laws
    made = [make_law(name, robot, config.period_s, config.gain_set) for name in laws]
    if policy_dir is not None:
        from models.lmpc import make_lmpc_controller

        controllers = [make_lmpc_controller(law, robot, bundle_dir=policy_dir) for law in made]
    elif config.target == "law":
        controllers = [FeedbackController(law) for law in made]
    else:
        controllers = [make_hmpc_controller(law, robot, **config.hmpc_options) for law in made]
    inertia0 = None
    if policy_dir is None and config.target == "hmpc" and config.accel_noise_rad_s2 > 0:
        from models.dynamics import make_dynamics

        n = robot.n_joints
        inertia0 = np.diag(np.asarray(make_dynamics(robot, "rne").mass_matrix(np.zeros(n))).reshape(n, n))
    group_logs = []
    for members, world in rollout_groups(config, conditions, robot, draw_seed):
        excite = None
        if inertia0 is not None:
            rows_on = (np.arange(len(members)) < round(config.noise_fraction * len(members))).astype(float)
            excite = (config.accel_noise_rad_s2 * inertia0, rows_on)
        group_logs.append(
            _logged_rollouts(
                robot,
                controllers,
                made,
                members,
                sim,
                config.stride,
                excite,
                config.noise_hold_steps,
                config.seed,
                log_previous=config.previous_torque,
                realism=world,
            )
        )
    logs = [{k: np.concatenate([g[i][k] for g in group_logs]) for k in group_logs[0][i]} for i in range(len(made))]
    # Runs that left the limits are dropped from the data; a law with none left has nothing to learn from
    # (and its relabeling would be handed zero states): say so in one line, not a traceback downstream.
    empty = [name for name, log in zip(laws, logs, strict=True) if len(log["q"]) == 0]
    if empty:
        who = "LMPC" if policy_dir is not None else ("FB" if config.target == "law" else "HMPC")
        raise ModelInputError(
            f"structured LMPC data on {robot.name}: every {who} rollout of {', '.join(empty)} left the joint limits "
            f"or went non-finite on the {len(conditions)} training conditions; nothing to learn from"
        )
    data = {}
    for name, law, log in zip(laws, made, logs, strict=True):
        if config.previous_torque:  # ROW_KINDS: which label a row has (the fit's two stages pick by it)
            log["row_kind"] = np.full((len(log["q"]), 1), 0.0 if policy_dir is None else 2.0)
        if policy_dir is not None and config.target == "hmpc":  # DAgger: given the LMPC's tau_0 if it reads one
            log["tau_star"] = relabel(law, robot, log, config.hmpc_options, executor, previous=config.previous_torque)
        elif config.target == "law":
            log["tau_star"] = log["tau_fb"].copy()
        if policy_dir is None and config.perturbed_copies > 0 and config.target == "hmpc":
            extra = perturbed(
                log, config.perturbed_copies, config.perturb_error_rad, config.perturb_rate_rad_s, config.seed + 17
            )
            with np.errstate(all="ignore"):
                extra["tau_fb"] = np.asarray(
                    law.step(
                        np, extra["law_state"], extra["q"], extra["qd"], extra["q_d"], extra["qd_d"], extra["qdd_d"]
                    )[0],
                    float,
                )
            extra["tau_star"] = relabel(law, robot, extra, config.hmpc_options, executor)
            if config.previous_torque:  # cold copies: the static optimum; rate copies: given a moved tau_0
                extra["row_kind"] = np.full((len(extra["q"]), 1), ROW_KINDS["static"])
                rate = rate_copies(law, robot, log, config)
                rate["tau_star"] = relabel(law, robot, rate, config.hmpc_options, executor, previous=True)
                extra = {k: np.concatenate([extra[k], rate[k]]) for k in extra}
            log = {k: np.concatenate([log[k], extra[k]]) for k in log}
        data[name] = log
    return data


def rollout_groups(
    config: StructuredConfig, conditions: list[Any], robot: RobotModel, draw_seed: int | None = None
) -> list[tuple[list[Any], Any]]:
    """The simulator batches of the training rollouts: (conditions, world). Condition i runs in draw
    i mod ``config.realism_draws`` of the randomized world (``config.train_realism``; None: one ideal world);
    a batch holds conditions of one draw sharing duration, disturbance and mismatch (envelope conditions
    have several disturbance times)."""
    worlds: list[Any] = [None]
    if config.train_realism is not None:
        from models.lmpc.structured.randomization import randomized_realism
        from sim_target.realism_profiles import load_realism

        base = load_realism(
            config.train_realism,
            robot.n_joints,
            config.period_s,
            config.period_s / config.substeps,
            robot.torque_limit_nm,
        )
        first = config.train_seed if draw_seed is None else draw_seed
        worlds = [randomized_realism(base, first * 100 + k) for k in range(config.realism_draws)]
        worlds += [None] * config.ideal_draws
    groups: dict[tuple, list[Any]] = {}
    for i, condition in enumerate(conditions):
        key = (i % len(worlds), *batch_key(condition))
        groups.setdefault(key, []).append(condition)
    return [(members, worlds[key[0]]) for key, members in groups.items()]


#: ``row_kind`` of a logged row (config.previous_torque): its label is the expert's applied torque given its
#: tau_0 (0, on-policy), a cold solve without tau_0 (1: the static optimum), a solve given the row's
#: tau_prev (2: rate copies, DAgger rows). The rate-aware fit uses 0 and 2.
ROW_KINDS = {"on_policy": 0.0, "static": 1.0, "rate": 2.0}


def perturbed(
    log: dict[str, np.ndarray], copies: int, sigma_e: float, sigma_rate: float, seed: int
) -> dict[str, np.ndarray]:
    """``copies`` perturbed copies of logged rows (module StructuredConfig.perturbed_copies); labels not set."""
    rng = np.random.default_rng(seed)
    rows = {k: np.concatenate([v] * copies) for k, v in log.items() if k != "tau_star"}
    rows["q"] = rows["q"] + rng.normal(0.0, sigma_e, rows["q"].shape)
    rows["qd"] = rows["qd"] + rng.normal(0.0, sigma_rate, rows["qd"].shape)
    return rows


def rate_copies(law: Any, robot: RobotModel, log: dict[str, np.ndarray], config: StructuredConfig) -> dict:
    """Every ``rate_copy_stride``-th logged row with e, e_dot perturbed (the static copies' sigmas) and
    tau_prev moved by N(0, rate_perturb_steps x the joint's torque step per period), all times a per-row
    scale: the rows that identify how far the expert steps from tau_0 (config.previous_torque); labels not
    set, ``row_kind`` 2."""
    from hil_runtime.rate_limit import max_torque_step_nm

    rows = {k: v[:: config.rate_copy_stride].copy() for k, v in log.items() if k != "tau_star"}
    rng = np.random.default_rng(config.seed + 29)
    # one log-uniform scale per row in [1e-2, 1] of the perturbation: at full scale the expert's step sits on
    # the rate bound (a 1 mrad error asks for several N m), at 1e-2 it is inside it; beta is seen on the latter
    scale = np.exp(rng.uniform(np.log(1e-2), 0.0, (len(rows["q"]), 1)))
    shape = rows["q"].shape
    rows["q"] = rows["q"] + scale * rng.normal(0.0, config.perturb_error_rad, shape)
    rows["qd"] = rows["qd"] + scale * rng.normal(0.0, config.perturb_rate_rad_s, shape)
    step = max_torque_step_nm(robot.torque_rate_nm_s, config.period_s)
    limit = np.asarray(robot.torque_limit_nm, float)
    moved = rows["tau_prev"] + scale * rng.normal(0.0, 1.0, shape) * config.rate_perturb_steps * step
    rows["tau_prev"] = np.clip(moved, -limit, limit)  # a commanded torque is within the limits
    with np.errstate(all="ignore"):
        rows["tau_fb"] = np.asarray(
            law.step(np, rows["law_state"], rows["q"], rows["qd"], rows["q_d"], rows["qd_d"], rows["qdd_d"])[0], float
        )
    rows["row_kind"] = np.full((len(rows["q"]), 1), 2.0)
    return rows


def relabel(
    law: Any,
    robot: RobotModel,
    log: dict[str, np.ndarray],
    hmpc_options: dict[str, Any],
    executor: Executor | None = None,
    previous: bool = False,
) -> np.ndarray:
    """The HMPC torque at logged states (cold solves from the logged law state), in chunks of 1024
    on ``executor``'s workers (models.executors; None: this process). ``previous``: each row's logged
    ``tau_prev`` is the solve's tau_0 (smoothness term and rate bound active); else the static optimum."""
    from models.hmpc import HMPCConfig, solve_batch

    options = {**hmpc_options, "on_budget_exhausted": "best_iterate"}
    rows = (log[k] for k in ("q", "qd", "q_d", "qd_d", "qdd_d", "law_state"))
    tau, _ = solve_batch(
        law,
        robot,
        *rows,
        config=HMPCConfig.from_options(**options),
        executor=executor,
        chunk_states=1024,
        previous_torque_nm=log["tau_prev"] if previous else None,
    )
    return tau


def features(log: dict[str, np.ndarray]) -> np.ndarray:
    """s = (q, e, qd, e_dot, qdd_d, tau_fb) of logged rows."""
    return np.concatenate(
        [log["q"], log["q_d"] - log["q"], log["qd"], log["qd_d"] - log["qd"], log["qdd_d"], log["tau_fb"]], 1
    )


_DATA_FIELDS = (
    "robot",
    "gain_set",
    "hmpc_options",
    "target",
    "train_conditions",
    "train_seed",
    "duration_s",
    "stride",
    "period_s",
    "substeps",
    "accel_noise_rad_s2",
    "noise_hold_steps",
    "noise_fraction",
    "perturbed_copies",
    "perturb_error_rad",
    "perturb_rate_rad_s",
    "seed",
    "previous_torque",
    "rate_copy_stride",
    "rate_perturb_steps",
    "rate_data",
)
#: data fields keyed only when they differ from their default (a cache made before they existed stays valid)
_OPTIONAL_DATA_FIELDS = ("train_realism", "realism_draws", "ideal_draws", "envelope_conditions")


#: the rate-aware recipe's version in the cache key (2: static and rate copies; 1, rate copies only, is stale)
RATE_DATA_VERSION = 2


def _data_key(config: StructuredConfig) -> str:
    """What the rollouts depend on (a cache made with other settings is not reused)."""
    values = {**jsonable_config(config), "rate_data": RATE_DATA_VERSION if config.previous_torque else 0}
    key = {k: values[k] for k in _DATA_FIELDS}
    defaults = StructuredConfig.__dataclass_fields__
    key.update({k: values[k] for k in _OPTIONAL_DATA_FIELDS if getattr(config, k) != defaults[k].default})
    return json.dumps(key, sort_keys=True)


def _cached_rollouts(
    work: Path,
    config: StructuredConfig,
    conditions: list[Any],
    log: Callable[[str], None],
    executor: Executor | None = None,
) -> dict[str, Any]:
    """Per law, <work>/rollouts_<law>.pkl when made with the same settings; the missing laws are run
    (side by side in one plant) and cached."""
    import pickle

    key = _data_key(config)
    data: dict[str, Any] = {}
    for name in config.laws:
        path = work / f"rollouts_{name}.pkl"
        if path.exists():
            try:
                stored_key, value = pickle.loads(path.read_bytes())
                if stored_key == key:
                    data[name] = value
            except Exception:  # noqa: BLE001, S110 - an unreadable cache is regenerated, never trusted
                pass
    if data:
        log(f"rollouts: reusing {', '.join(sorted(data))} from {work}")
    missing = tuple(name for name in config.laws if name not in data)
    if missing:
        fresh = collect(config, conditions, law_names=missing, executor=executor)
        for name in missing:
            path = work / f"rollouts_{name}.pkl"
            tmp = path.with_suffix(".tmp")
            tmp.write_bytes(pickle.dumps((key, fresh[name])))
            tmp.replace(path)
            data[name] = fresh[name]
    return {name: data[name] for name in config.laws}
