"""Bundles of a trained structured emulator (through models.lmpc.bundle_export), the trained file that
keeps what an export needs, and re-export from it without rollouts or a refit."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from models.errors import ModelInputError
from models.feedback import make_law
from models.lmpc.structured.config import TRAINED_FORMAT, StructuredConfig, config_from_json, jsonable_config
from models.lmpc.structured.graph import structured_policy_class
from models.lmpc.structured.model import StructuredEmulator
from models.robots import RobotModel, load_robot


def export_structured(
    out_dir: Path,
    law_name: str,
    robot: RobotModel,
    model: StructuredEmulator,
    s: np.ndarray,
    y: np.ndarray,
    config: StructuredConfig,
    summary: dict[str, Any],
) -> dict[str, Any]:
    """A policy bundle through models.lmpc.bundle_export (trust region: the training states' box)."""
    box, label_max = trust_box(s, robot, config), np.abs(y).max(0)
    return export_trained(out_dir, law_name, robot, model, box, label_max, config, summary)


def export_trained(
    out_dir: Path,
    law_name: str,
    robot: RobotModel,
    model: StructuredEmulator,
    box: tuple[np.ndarray, np.ndarray],
    label_max_nm: np.ndarray,
    config: StructuredConfig,
    summary: dict[str, Any],
) -> dict[str, Any]:
    """export_structured from what it needs of the data: the trust box and max |tau* - tau_fb| per joint
    (what ``save_trained`` keeps, so a bundle can be re-exported without the rollouts or a refit)."""
    from models.lmpc.bundle_export import export_bundle

    law = make_law(law_name, robot, config.period_s, config.gain_set)
    low, high = box
    bound = config.bound_scale * np.asarray(label_max_nm, float) + 1e-3
    training = {
        "design": "structured (models/lmpc/structured/, docs/lmpc.md section 9)",
        "gain_set": config.gain_set,
        "config": jsonable_config(config),
        "summary": summary,
        "structure": "r = c*tau_fb + g*ID(p, qdd_d + kp*e + kd*e_dot) + b*tanh(MLP(s)/b); p = "
        + ("(q, qd) measured" if config.ff_point == "measured" else "(q_d, qd_d) reference")
        + (
            "; tau = sat(tau_prev + clip((1 - alpha (1 - beta)) (target - tau_prev), +-rate step)), target = the "
            "trust region's torque (docs/lmpc.md section 11)"
            if config.previous_torque
            else ""
        ),
        "trust": {
            "box": "min/max of the training states, at least the paper's range (q, qd, qdd_d) 10 % beyond, "
            "e, e_dot +-error/rate envelopes, tau_fb the torque limits",
            "box_margin": config.box_margin,
            "residual_bound": f"{config.bound_scale} x max |tau* - tau_fb| over the training labels",
        },
    }
    validation = {
        "physics_relative_loss": summary["physics"]["relative_loss"],
        "residual_val_relative_loss": summary["residual"]["val_relative_loss"],
    }
    # onnxruntime-vs-torch parity on the exporter's seeded random rows; probes recorded by the exporter
    return export_bundle(
        out_dir,
        law,
        robot,
        model,
        training,
        validation,
        trust_region=(low, high),
        residual=True,
        residual_bound_nm=bound,
        box_margin=config.box_margin,
        feature_set="eq22+qdd_d",
        policy_class=structured_policy_class(),
    )


def trust_box(s: np.ndarray, robot: RobotModel, config: StructuredConfig) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) of the trust box over s = (q, e, qd, e_dot, qdd_d, tau_fb); see StructuredConfig."""
    from models.lmpc.paper_range import PAPER_AMPLITUDE_RAD, PAPER_FREQUENCY_RANGE_HZ

    n = robot.n_joints
    low, high = s.min(0).copy(), s.max(0).copy()
    # the paper's range (models.lmpc.paper_range), 10 % beyond: where the physics part was trained to hold
    omega = 2.0 * np.pi * PAPER_FREQUENCY_RANGE_HZ[1]
    reference = (
        1.1 * PAPER_AMPLITUDE_RAD,
        1.1 * 0.5 * PAPER_AMPLITUDE_RAD * omega * 2.0,
        1.1 * 0.5 * PAPER_AMPLITUDE_RAD * omega**2,
    )
    for block, envelope in (
        (0, reference[0]),
        (2, reference[1]),
        (4, reference[2]),
        (1, config.error_envelope_rad),
        (3, config.rate_envelope_rad_s),
        (5, np.asarray(robot.torque_limit_nm, float)),
    ):
        part = slice(block * n, (block + 1) * n)
        low[part] = np.minimum(low[part], -envelope)
        high[part] = np.maximum(high[part], envelope)
    return low, high


def save_trained(
    path: Path,
    model: StructuredEmulator,
    config: StructuredConfig,
    fit: dict[str, Any],
    box: tuple[np.ndarray, np.ndarray],
    label_max_nm: np.ndarray,
) -> None:
    """The trained emulator (torch weights, frozen coefficients) and what its export needs of the data:
    ``reexport`` rebuilds the bundle from it (another residual bound, a changed graph) without a refit."""
    payload = {
        "format": TRAINED_FORMAT,
        "config": jsonable_config(config),
        "state_dict": model.state_dict(),
        "frozen": [t.detach().clone() for t in model.coefficients()],
        "use_residual": bool(model.use_residual),
        "fit": fit,
        "box": [np.asarray(box[0], float), np.asarray(box[1], float)],
        "label_max_nm": np.asarray(label_max_nm, float),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)


def reexport(
    work: Path,
    bundles: Path,
    laws: tuple[str, ...] = (),
    bound_scale: float | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Bundles from run_structured's trained files (<work>/trained_<law>.pt) with today's graph code: no
    rollouts, no refit. ``bound_scale`` overrides the recorded residual-bound scale."""
    work, bundles = Path(work), Path(bundles)
    names = laws or tuple(sorted(p.stem.removeprefix("trained_") for p in work.glob("trained_*.pt")))
    if not names:
        raise ModelInputError(f"reexport: no trained_<law>.pt in {work} (made by `hil pipeline --design structured`)")
    summary: dict[str, Any] = {}
    for name in names:
        path = work / f"trained_{name}.pt"
        if not path.is_file():
            raise ModelInputError(f"reexport: {path}: missing")
        try:
            payload = torch.load(path, weights_only=False)
        except Exception as exc:  # noqa: BLE001 - torch raises pickle, zip and runtime errors alike
            raise ModelInputError(f"reexport: {path}: unreadable ({str(exc).splitlines()[0][:120]})") from None
        if not isinstance(payload, dict) or payload.get("format") != TRAINED_FORMAT:
            raise ModelInputError(f"reexport: {path}: not a {TRAINED_FORMAT} file")
        config = config_from_json(payload["config"])
        if bound_scale is not None:
            config = replace(config, bound_scale=float(bound_scale))
        robot = load_robot(config.robot)
        bound = config.residual_bound_fraction * np.asarray(robot.torque_limit_nm, float)
        model = StructuredEmulator(
            robot, config.hidden, bound, config.ff_point, config.c_max, config.previous_torque, config.period_s
        )
        model.load_state_dict(payload["state_dict"])
        model.frozen = tuple(payload["frozen"])
        model.use_residual = bool(payload["use_residual"])
        box = (payload["box"][0], payload["box"][1])
        out = bundles / robot.name / name
        manifest = export_trained(out, name, robot, model.eval(), box, payload["label_max_nm"], config, payload["fit"])
        error = float(manifest["validation"]["onnx_vs_torch_max_abs_nm"])
        summary[name] = {"path": str(out), "bound_scale": config.bound_scale, "onnx_vs_torch_max_abs_nm": error}
        log(f"{name}: re-exported {out} (residual bound {config.bound_scale}x; onnx vs torch {error:.1e} N m)")
    return summary
