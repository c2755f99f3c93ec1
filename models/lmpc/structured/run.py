"""The whole structured stage: rollouts -> fit -> export (-> DAgger rounds)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from hil_runtime.bundle import DEFAULT_ENCODER_NOISE_RAD, PolicyBundle
from models.executors import Executor
from models.lmpc.structured.config import StructuredConfig, jsonable_config
from models.lmpc.structured.data import ROW_KINDS, _cached_rollouts, collect, features
from models.lmpc.structured.export import export_trained, save_trained, trust_box
from models.lmpc.structured.model import StructuredEmulator
from models.lmpc.structured.training import fit_beta, rate_aware, train_structured
from models.robots import RobotModel, load_robot


def run_structured(
    config: StructuredConfig,
    bundles: Path,
    work: Path,
    log: Callable[[str], None] = print,
    executor: Executor | None = None,
) -> dict[str, Any]:
    """Rollouts -> fit -> export (-> DAgger rounds); returns a summary (also written to work/structured.json).
    The cold HMPC relabeling runs on ``executor`` (models.executors; None: this process)."""
    robot = load_robot(config.robot)
    work.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    conditions = training_conditions(robot, config, config.train_conditions, config.train_seed, "T")
    if config.train_realism is not None:
        log(f"rollouts: domain-randomized around {config.train_realism} ({config.realism_draws} draws)")
    data = _cached_rollouts(work, config, conditions, log, executor)
    counts = ", ".join(f"{k} {len(v['q'])}" for k, v in data.items())
    log(f"rollouts: {counts} states ({time.perf_counter() - started:.0f} s)")
    summary: dict[str, Any] = {"config": jsonable_config(config), "rounds": []}
    for round_index in range(config.dagger_rounds + 1):
        per_law = {}
        for name in config.laws:
            # the static part on the expert's states and the cold copies (the rate copies' labels depend on tau_0)
            kinds = tuple(ROW_KINDS[k] for k in config.static_rows)
            rows = _rows(data[name], config.previous_torque, kinds)
            s, y = features(rows), rows["tau_star"] - rows["tau_fb"]
            log(f"{name}: fit on {len(s)} states (round {round_index})")
            model, fit = train_structured(robot, s, y, config, log)
            if config.previous_torque:  # then beta, on the rows labeled given their tau_0 (docs/lmpc.md §11)
                model = rate_aware(model, robot, config)
                given = _rows(data[name], True, (ROW_KINDS["on_policy"], ROW_KINDS["rate"]))
                prev, star = given["tau_prev"], given["tau_star"]
                fit["rate"] = fit_beta(model, features(given), prev, star, config.beta_floor, log)
            box, label_max = trust_box(s, robot, config), np.abs(y).max(0)
            if config.previous_torque and config.rate_check:
                fit["rate"].update(
                    rate_feasible_bandwidth(model, name, robot, config, conditions, box, label_max, fit, log)
                )
            save_trained(work / f"trained_{name}.pt", model, config, fit, box, label_max)
            manifest = export_trained(bundles / robot.name / name, name, robot, model, box, label_max, config, fit)
            tolerated = PolicyBundle.load(bundles / robot.name / name).tolerated_encoder_noise_rad()
            limit = "any noise (bounded steps)" if tolerated == float("inf") else f"{tolerated:.2g} rad RMS"
            log(f"{name}: the runtime's sensing gate (docs/runtime.md) accepts this bundle on encoders up to {limit}")
            if tolerated < DEFAULT_ENCODER_NOISE_RAD:
                log(
                    f"{name}: below the runtime's default {DEFAULT_ENCODER_NOISE_RAD:g} rad (a 19-bit encoder): "
                    "refused on such an arm; --tau-prev bundles bound their steps in the graph"
                )
            per_law[name] = {
                "fit": fit,
                "onnx_vs_torch_max_abs_nm": manifest["validation"]["onnx_vs_torch_max_abs_nm"],
                "tolerated_encoder_noise_rad": tolerated,
            }
        summary["rounds"].append(per_law)
        if round_index == config.dagger_rounds:
            break
        seed = config.dagger_seed + round_index
        dagger = training_conditions(robot, config, config.dagger_conditions, seed, "D")
        extra = collect(config, dagger, policy_dir=bundles, executor=executor, draw_seed=seed)
        for name in config.laws:
            data[name] = {k: np.concatenate([data[name][k], extra[name][k]]) for k in data[name]}
        counts = ", ".join(f"{k} {len(v['q'])}" for k, v in extra.items())
        log(f"DAgger round {round_index + 1}: + {counts} states")
    summary["wall_s"] = time.perf_counter() - started
    (work / "structured.json").write_text(json.dumps(summary, indent=1, default=float))
    return summary


def training_conditions(robot: RobotModel, config: StructuredConfig, count: int, seed: int, prefix: str) -> list[Any]:
    """``count`` paper-range conditions (models.lmpc.paper_range) and, with ``config.envelope_conditions``,
    as many more across the arm's envelope (models.envelope_conditions: offsets, holds, 80 % of the limits,
    the disturbance at random times), all lasting ``config.duration_s``; seeded by ``seed``."""
    from models.envelope_conditions import envelope_conditions
    from models.lmpc.paper_range import paper_range_conditions

    out = paper_range_conditions(robot, count, seed, prefix=prefix)
    if config.envelope_conditions:
        out += envelope_conditions(robot, config.envelope_conditions, seed, prefix=f"{prefix}E")
    return [replace(c, duration_s=config.duration_s) for c in out]


#: bandwidth scales tried, largest first, for the rate-aware static part (K_p s^2, K_d s)
BANDWIDTH_SCALES = (1.0, 0.7, 0.5, 0.35, 0.25)
#: training conditions the rate-aware closed loop is checked on (each with its disturbance)
RATE_CHECK_CONDITIONS = 4


def rate_feasible_bandwidth(
    model: StructuredEmulator,
    law_name: str,
    robot: RobotModel,
    config: StructuredConfig,
    conditions: list[Any],
    box: tuple[np.ndarray, np.ndarray],
    label_max: np.ndarray,
    fit: dict[str, Any],
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """The bandwidth scale s (K_p s^2, K_d s: the static part's error dynamics slowed by s) whose rate-aware
    closed loop stays inside the limits, below the torque limit, on the most of the first training
    conditions; among equals the largest (the fitted gains, s = 1, unless a slower loop holds more).

    Why: the static gains are fitted on the HMPC's unbounded solves; where they ask for more torque rate than
    the bound allows after a disturbance (the real UR5: K_p 2200-4600 1/s^2 against 1 N m per cycle), the
    rate-limited loop limit-cycles from bound to bound and leaves the limits (docs/any_arm.md, "Rate-aware
    bundles on the real arms"). The HMPC does not: it previews the bound. Slowing the error dynamics until
    the bounded loop holds is the smallest change that keeps the structure; it is checked on training
    conditions only (the experiment's conditions are never seen). The model's gains are scaled in place."""
    import tempfile

    from models.feedback import make_law
    from models.lmpc.controller import make_lmpc_controller
    from models.sim import SimConfig, simulate

    if model.frozen is None:
        raise RuntimeError("rate_feasible_bandwidth: the static part must be fitted (frozen) first")
    c, g, kp, kd = model.frozen
    law = make_law(law_name, robot, config.period_s, config.gain_set)
    limit = np.asarray(robot.torque_limit_nm, float)
    checks = conditions[:RATE_CHECK_CONDITIONS]
    sim = SimConfig(period_s=config.period_s, substeps=config.substeps)
    tried: list[dict[str, Any]] = []
    for scale in BANDWIDTH_SCALES:
        model.frozen = (c, g, kp * scale**2, kd * scale)
        inside = 0
        with tempfile.TemporaryDirectory() as tmp:
            export_trained(Path(tmp) / robot.name / law_name, law_name, robot, model, box, label_max, config, fit)
            controller = make_lmpc_controller(law, robot, bundle_dir=tmp)
            for condition in checks:
                traj = simulate(robot, controller, [condition], sim)
                peak = float(np.nan_to_num(np.abs(traj.tau[0]) / limit, nan=np.inf).max())
                inside += int(bool(traj.within_limits.all()) and peak < 1.0 - 1e-9)
        tried.append({"scale": scale, "inside": inside})
        if inside == len(checks):
            break
    best = max(tried, key=lambda t: (t["inside"], t["scale"]))  # the most held, then the fastest
    model.frozen = (c, g, kp * best["scale"] ** 2, kd * best["scale"])
    outcome = ", ".join(f"{t['scale']}: {t['inside']}/{len(checks)}" for t in tried)
    log(f"  rate check: bandwidth scale {best['scale']} (inside at {outcome})")
    return {
        "bandwidth_scale": best["scale"],
        "bandwidth_checked": tried,
        "bandwidth_feasible": best["inside"] == len(checks),
    }


def _rows(data: dict[str, np.ndarray], by_kind: bool, kinds: tuple[float, ...]) -> dict[str, np.ndarray]:
    """The rows of ``data`` whose ``row_kind`` is one of ``kinds`` (all rows when not ``by_kind``)."""
    if not by_kind:
        return data
    keep = np.isin(data["row_kind"][:, 0], kinds)
    return {k: v[keep] for k, v in data.items()}
