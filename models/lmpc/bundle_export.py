"""Export a policy bundle: the law's step (explicit state) and the emulator fused in one ONNX graph.

    x (B, 5N+S) = [q, qd, q_d, qd_d, qdd_d, law_state]           float64
    tau_fb, law_state' = law.step(torch, law_state, q, qd, q_d, qd_d, qdd_d)
    s = (q, q_d - q, qd, qd_d - qd, [qdd_d,] tau_fb)              feature set "eq22" or "eq22+qdd_d"
    r = emulator(s)                                               normalization inside the graph;
                                                                  residual target: r ~ tau* - tau_fb
    tau = trust region (hil_runtime.bundle): sat(tau_fb) outside the training box (of the guard
          features (q, e, qd, e_dot, qdd_d, tau_fb), whatever the emulator's inputs),
          else sat(tau_fb + clip(r, -bound, bound))
    an emulator with ``previous_torque`` (models.lmpc.structured, docs/lmpc.md §11): x also holds
    tau_prev (the input layout's last slot, N), and tau = sat(tau_prev + clip(share (target - tau_prev),
    +-step)) with target the trust region's torque above, share = 1 - alpha (1 - beta), step the robot's
    torque-rate bound x the period (the bundle itself meets the rate rule)
    law_state'[applied_torque_slice] = tau                        (ADRC's observer input)
    y (B, 2N+S+2) = [tau, tau_fb, law_state', trust]              trust = [1 - alpha, joints_clamped]

The manifest (one schema with the loader: hil_runtime.bundle_schema; probes recorded for its
behavioural check) carries everything the runtime checks, and the provenance of the training.
``verify_bundle`` checks onnxruntime against torch (<= 1e-5 N m).
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from hil_runtime.bundle import PolicyBundle, record_probes, sha256_file
from hil_runtime.bundle_schema import (
    FEATURE_SETS,
    GUARD_FEATURES,
    INPUT_LAYOUT,
    MANIFEST,
    OUTPUT_LAYOUT,
    PREVIOUS_TORQUE,
    SCHEMA,
    TRUST_MIN_SPAN,
    TRUST_SIZE,
    Manifest,
)
from hil_runtime.bundle_security import write_manifest
from hil_runtime.trust_region import named_features
from models.errors import ModelInputError
from models.feedback.base import FeedbackLaw
from models.lmpc.dataset import jsonable
from models.lmpc.emulator import Emulator
from models.robots import RobotModel

GRAPH_FILE = "policy.onnx"
OPSET = 17
PARITY_TOLERANCE_NM = 1e-5


class FusedPolicy(nn.Module):
    """Law step + emulator + saturation + applied-torque bookkeeping, one packed row in and out."""

    def __init__(
        self,
        law: FeedbackLaw,
        emulator: Emulator,
        residual: bool = False,
        trust: dict[str, Any] | None = None,
        feature_set: str | None = None,
    ) -> None:
        super().__init__()
        n_features = emulator.in_mean.numel()
        if feature_set is None:  # by width: the paper's Eq. 22 (5N) or Eq. 22 + qdd_d (6N)
            feature_set = {5 * law.n_joints: "eq22", 6 * law.n_joints: "eq22+qdd_d"}.get(n_features, "?")
        if feature_set not in FEATURE_SETS or len(FEATURE_SETS[feature_set]) * law.n_joints != n_features:
            raise ModelInputError(
                f"bundle export: emulator takes {n_features} inputs, feature set {feature_set!r} does not fit"
            )
        self.feature_set = feature_set
        self.residual = residual
        width = len(FEATURE_SETS[GUARD_FEATURES]) * law.n_joints
        box = trust is not None
        low = np.asarray(trust["feature_low"], float) if box else np.full(width, -1e300)
        high = np.asarray(trust["feature_high"], float) if box else np.full(width, 1e300)
        margin = float(trust["box_margin"]) if box else 1.0
        bound = trust.get("residual_bound_nm") if box else None
        self.register_buffer("box_low", torch.as_tensor(low, dtype=torch.float64))
        self.register_buffer("box_high", torch.as_tensor(high, dtype=torch.float64))
        self.register_buffer(
            "box_inv_span", torch.as_tensor(1.0 / np.maximum(high - low, TRUST_MIN_SPAN), dtype=torch.float64)
        )
        self.inv_margin = 1.0 / max(margin, 1e-12)
        self.register_buffer(
            "bound",
            torch.as_tensor(
                np.full(law.n_joints, 1e300) if bound is None else np.asarray(bound, float), dtype=torch.float64
            ),
        )
        # (H-infinity's and SMC's nominal model traces to models.dynamics.torch_rne, the small RNE graph)
        self.law = law
        self.emulator = emulator.double().eval()
        self.n, self.s = law.n_joints, law.state_size
        self.register_buffer("limit", torch.as_tensor(law.torque_limit_nm, dtype=torch.float64))
        self.applied = law.applied_torque_slice
        self.previous = bool(getattr(emulator, "previous_torque", False))  # x ends with tau_prev (N)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n = self.n
        q, qd, q_d, qd_d, qdd_d = (x[:, i * n : (i + 1) * n] for i in range(5))
        state = x[:, 5 * n : 5 * n + self.s]
        tau_fb, next_state = self.law.step(torch, state, q, qd, q_d, qd_d, qdd_d)
        named = named_features(q, qd, q_d, qd_d, qdd_d, tau_fb)  # the runtime's own feature names
        s = torch.cat([named[k] for k in FEATURE_SETS[self.feature_set]], 1)
        guard = torch.cat([named[k] for k in FEATURE_SETS[GUARD_FEATURES]], 1)
        r = self.emulator(s)
        if not self.residual:
            r = r - tau_fb
        excess = torch.clamp(torch.maximum(self.box_low - guard, guard - self.box_high), min=0.0) * self.box_inv_span
        alpha = torch.clamp(1.0 - torch.amax(excess, 1, keepdim=True) * self.inv_margin, 0.0, 1.0)
        clamped = torch.sum((torch.abs(r) > self.bound).to(torch.float64), 1, keepdim=True) * (alpha > 0).to(
            torch.float64
        )
        r = torch.minimum(torch.maximum(r, -self.bound), self.bound)
        tau = tau_fb + alpha * r
        if self.previous:
            tau = self.emulator.rate_step_from(tau, x[:, 5 * n + self.s : 6 * n + self.s], alpha)
        tau = torch.minimum(torch.maximum(tau, -self.limit), self.limit)
        if self.applied is not None:
            a, b = self.applied.start, self.applied.stop
            next_state = torch.cat([next_state[:, :a], tau, next_state[:, b:]], 1)
        parts = [tau, tau_fb] + ([next_state] if self.s else []) + [1.0 - alpha, clamped]
        return torch.cat(parts, 1)


def initial_state_map(law: FeedbackLaw) -> tuple[np.ndarray, np.ndarray]:
    """(constant (S,), position_gain (S, N)) with initial_state(q0) = constant + gain q0, checked affine."""
    n = law.n_joints
    constant = law.initial_state(np.zeros((1, n)))[0]
    gain = np.stack([law.initial_state(np.eye(n)[j : j + 1])[0] - constant for j in range(n)], 1).reshape(
        law.state_size, n
    )
    probe = np.random.default_rng(0).normal(size=(3, n))
    if not np.allclose(law.initial_state(probe), constant + probe @ gain.T, atol=1e-9):
        raise ModelInputError(f"bundle export: law '{law.name}' initial state is not affine in q0")
    return constant, gain


def export_bundle(
    out_dir: Path,
    law: FeedbackLaw,
    robot: RobotModel,
    emulator: Emulator,
    training: dict[str, Any],
    validation: dict[str, Any],
    trust_region: tuple[np.ndarray, np.ndarray] | None = None,
    parity_inputs: np.ndarray | None = None,
    residual: bool = False,
    residual_bound_nm: np.ndarray | None = None,
    box_margin: float = 0.1,
    feature_set: str | None = None,
    policy_class: type | None = None,
) -> dict[str, Any]:
    """Write the bundle directory (atomically: a temporary sibling renamed at the end); return the manifest.

    ``residual``: the emulator predicts tau* - tau_fb (its zero is the feedback law). ``trust_region``
    (feature box of the training inputs), ``residual_bound_nm`` and ``box_margin``: the trust region
    applied in the graph and written to the manifest (hil_runtime.bundle documents the rule).
    """
    n, s = law.n_joints, law.state_size
    out_dir = Path(out_dir)
    tmp = out_dir.with_name(f".{out_dir.name}.tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        trust = (
            None
            if trust_region is None
            else {
                "features": GUARD_FEATURES,
                "feature_names": list(FEATURE_SETS[GUARD_FEATURES]),
                "feature_low": np.asarray(trust_region[0], float).tolist(),
                "feature_high": np.asarray(trust_region[1], float).tolist(),
                "box_margin": float(box_margin),
                "residual_bound_nm": None
                if residual_bound_nm is None
                else np.asarray(residual_bound_nm, float).tolist(),
                "rule": "d = max_j max(low_j - g_j, g_j - high_j, 0) / (high_j - low_j); "
                "alpha = clip(1 - d / box_margin, 0, 1); "
                "tau = sat(tau_fb + alpha clip(tau_L - tau_fb, -residual_bound_nm, residual_bound_nm)); "
                "alpha = 0: fallback to the feedback law (hil_runtime.bundle)",
                "bound_source": "per-joint percentile of |tau* - tau_fb| over the training labels (training.trust)",
            }
        )
        # policy_class: a FusedPolicy subclass with the same inputs/outputs (models.lmpc.structured)
        model = (policy_class or FusedPolicy)(law, emulator, residual, trust, feature_set).eval()
        example = torch.zeros(2, (6 if model.previous else 5) * n + s, dtype=torch.float64)
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(
                model,
                (example,),
                str(tmp / GRAPH_FILE),
                input_names=["x"],
                output_names=["y"],
                dynamic_axes={"x": {0: "batch"}, "y": {0: "batch"}},
                opset_version=OPSET,
                dynamo=False,
            )
        constant, gain = initial_state_map(law)
        manifest = {
            "schema": SCHEMA,
            "robot": {
                "name": robot.name,
                "urdf_file": robot.urdf_path.name,
                "urdf_sha256": sha256_file(robot.urdf_path),
                "n_joints": n,
                "joint_names": list(robot.joint_names),
            },
            "period_s": law.period_s,
            "limits": {
                "position_rad": robot.position_limit_rad.tolist(),
                "velocity_rad_s": robot.velocity_limit_rad_s.tolist(),
                "torque_nm": law.torque_limit_nm.tolist(),
                "torque_rate_nm_s": robot.torque_rate_nm_s.tolist(),  # hil_runtime.rate_limit
                # an asymmetric range (the Panda's): the runtime's soft limits are [lower, upper]
                **(
                    {}
                    if robot.position_range_rad is None
                    else {
                        "position_lower_rad": robot.position_lower_rad.tolist(),
                        "position_upper_rad": robot.position_upper_rad.tolist(),
                    }
                ),
            },
            "law": {
                "name": law.name,
                "params": jsonable(law.params),
                "gain_set": training.get("gain_set"),
                "state_size": s,
                "applied_torque_slice": None
                if law.applied_torque_slice is None
                else [law.applied_torque_slice.start, law.applied_torque_slice.stop],
                "initial_state": {"constant": constant.tolist(), "position_gain": gain.tolist()},
            },
            "graph": {
                "file": GRAPH_FILE,
                "opset": OPSET,
                "dtype": "float64",
                "input": {
                    "name": "x",
                    "layout": [{"name": k, "size": n if k != "law_state" else s} for k in INPUT_LAYOUT]
                    + ([{"name": PREVIOUS_TORQUE, "size": n}] if model.previous else []),
                },
                "output": {
                    "name": "y",
                    "layout": [
                        {"name": k, "size": {"next_law_state": s, "trust": TRUST_SIZE}.get(k, n)} for k in OUTPUT_LAYOUT
                    ],
                },
                "fused": "law step + emulator (normalization inside) + trust region + saturation"
                " + applied-torque state update",
            },
            "emulator": {
                "feature_set": model.feature_set,
                "features": list(FEATURE_SETS[model.feature_set]),
                "features_note": "e = q_d - q, e_dot = qd_d - qd; (q, e, qd, e_dot, tau_fb) is the paper's Eq. 22; "
                "'ref' = the reference only (docs/lmpc.md)",
                "residual": bool(residual),
                "target": "tau* - tau_fb (N m): the network's zero is the feedback law"
                if residual
                else "HMPC torque tau* (N m)",
                "hidden": list(emulator_hidden(emulator)),
                "activation": "relu",
                "output": "linear",
            },
            "trust_region": trust,
            "training": jsonable(training),
            "validation": jsonable(validation),
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        }
        manifest["files"] = {GRAPH_FILE: sha256_file(tmp / GRAPH_FILE)}
        Manifest.model_validate(manifest)  # the one schema the loader reads with (hil_runtime.bundle_schema)
        manifest = write_manifest(tmp / MANIFEST, manifest)  # sealed: bundle_id over its canonical form
        manifest["probes"] = record_probes(tmp)  # the loader's behavioural check reruns these
        manifest = write_manifest(tmp / MANIFEST, manifest)
        manifest["validation"]["onnx_vs_torch_max_abs_nm"] = verify_bundle(tmp, model, parity_inputs)
        Manifest.model_validate(manifest)
        manifest = write_manifest(tmp / MANIFEST, manifest)
        if out_dir.exists():
            shutil.rmtree(out_dir)
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp, out_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return manifest


def emulator_hidden(emulator: Emulator) -> tuple[int, ...]:
    return tuple(layer.out_features for layer in emulator.net if isinstance(layer, nn.Linear))[:-1]


def verify_bundle(bundle_dir: Path, model: FusedPolicy, inputs: np.ndarray | None = None) -> float:
    """Max |onnxruntime - torch| over ``inputs`` (default: seeded random rows); raises above 1e-5."""
    bundle = PolicyBundle.load(bundle_dir)
    width = bundle.input_width
    if inputs is None:
        rng = np.random.default_rng(0)
        inputs = rng.normal(size=(64, width)) * 0.5
    with torch.no_grad():
        expected = model(torch.as_tensor(inputs, dtype=torch.float64)).numpy()
    n, s = bundle.n_joints, bundle.state_size
    previous = inputs[:, 5 * n + s :] if bundle.takes_previous_torque else None
    tau, tau_fb, state = bundle.step_batch(
        *(inputs[:, i * n : (i + 1) * n] for i in range(5)), inputs[:, 5 * n : 5 * n + s], previous
    )
    got = np.concatenate([tau, tau_fb, state, bundle.last_trust_batch], 1)
    if bundle.previous_torque_nm is not None and previous is not None:
        bundle.previous_torque_nm[:] = previous[0]
    single = np.concatenate(
        [
            *bundle.step(*(inputs[0, i * n : (i + 1) * n] for i in range(5)), inputs[0, 5 * n : 5 * n + s]),
            bundle.last_trust,
        ]
    )
    error = float(max(np.abs(got - expected).max(), np.abs(single - expected[0]).max()))
    if not error <= PARITY_TOLERANCE_NM:
        raise ModelInputError(
            f"bundle {bundle_dir}: onnxruntime differs from torch by {error:.3g} (> {PARITY_TOLERANCE_NM})"
        )
    return error
