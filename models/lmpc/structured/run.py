"""The whole structured stage: rollouts -> fit -> export (-> DAgger rounds)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from models.executors import Executor
from models.lmpc.structured.config import StructuredConfig, jsonable_config
from models.lmpc.structured.data import ROW_KINDS, _cached_rollouts, collect, features
from models.lmpc.structured.export import export_trained, save_trained, trust_box
from models.lmpc.structured.training import fit_beta, rate_aware, train_structured
from models.robots import load_robot


def run_structured(
    config: StructuredConfig,
    bundles: Path,
    work: Path,
    log: Callable[[str], None] = print,
    executor: Executor | None = None,
) -> dict[str, Any]:
    """Rollouts -> fit -> export (-> DAgger rounds); returns a summary (also written to work/structured.json).
    The cold HMPC relabeling runs on ``executor`` (models.executors; None: this process)."""
    from models.lmpc.paper_range import paper_range_conditions

    robot = load_robot(config.robot)
    work.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    conditions = paper_range_conditions(robot, config.train_conditions, config.train_seed, prefix="T")
    conditions = [replace(c, duration_s=config.duration_s) for c in conditions]
    data = _cached_rollouts(work, config, conditions, log, executor)
    counts = ", ".join(f"{k} {len(v['q'])}" for k, v in data.items())
    log(f"rollouts: {counts} states ({time.perf_counter() - started:.0f} s)")
    summary: dict[str, Any] = {"config": jsonable_config(config), "rounds": []}
    for round_index in range(config.dagger_rounds + 1):
        per_law = {}
        for name in config.laws:
            # the static part on the expert's states and the cold copies (the rate copies' labels depend on tau_0)
            rows = _rows(data[name], config.previous_torque, (ROW_KINDS["on_policy"], ROW_KINDS["static"]))
            s, y = features(rows), rows["tau_star"] - rows["tau_fb"]
            log(f"{name}: fit on {len(s)} states (round {round_index})")
            model, fit = train_structured(robot, s, y, config, log)
            if config.previous_torque:  # then beta, on the rows labeled given their tau_0 (docs/lmpc.md §11)
                model = rate_aware(model, robot, config)
                given = _rows(data[name], True, (ROW_KINDS["on_policy"], ROW_KINDS["rate"]))
                prev, star = given["tau_prev"], given["tau_star"]
                fit["rate"] = fit_beta(model, features(given), prev, star, config.beta_floor, log)
            box, label_max = trust_box(s, robot, config), np.abs(y).max(0)
            save_trained(work / f"trained_{name}.pt", model, config, fit, box, label_max)
            manifest = export_trained(bundles / robot.name / name, name, robot, model, box, label_max, config, fit)
            per_law[name] = {"fit": fit, "onnx_vs_torch_max_abs_nm": manifest["validation"]["onnx_vs_torch_max_abs_nm"]}
        summary["rounds"].append(per_law)
        if round_index == config.dagger_rounds:
            break
        dagger = paper_range_conditions(robot, config.dagger_conditions, config.dagger_seed + round_index, prefix="D")
        dagger = [replace(c, duration_s=config.duration_s) for c in dagger]
        extra = collect(config, dagger, policy_dir=bundles, executor=executor)
        for name in config.laws:
            data[name] = {k: np.concatenate([data[name][k], extra[name][k]]) for k in data[name]}
        counts = ", ".join(f"{k} {len(v['q'])}" for k, v in extra.items())
        log(f"DAgger round {round_index + 1}: + {counts} states")
    summary["wall_s"] = time.perf_counter() - started
    (work / "structured.json").write_text(json.dumps(summary, indent=1, default=float))
    return summary


def _rows(data: dict[str, np.ndarray], by_kind: bool, kinds: tuple[float, ...]) -> dict[str, np.ndarray]:
    """The rows of ``data`` whose ``row_kind`` is one of ``kinds`` (all rows when not ``by_kind``)."""
    if not by_kind:
        return data
    keep = np.isin(data["row_kind"][:, 0], kinds)
    return {k: v[keep] for k, v in data.items()}
