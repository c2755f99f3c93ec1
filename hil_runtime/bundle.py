"""Policy bundles: load, verify and step the exported feedback law + torque emulator.

A bundle is a directory written by ``models.lmpc.bundle_export`` (ARCHITECTURE.md, contract 1)::

    <bundle>/manifest.json   schema, robot + URDF sha256, joints, period, limits, law, layout,
                             training provenance, validation error, sha256 of every file
    <bundle>/policy.onnx     one fused graph: x (B, 5N+S) -> y (B, 2N+S+2), float64
                             x = [q, qd, q_d, qd_d, qdd_d, law_state]
                             y = [tau, tau_fb, next_law_state, trust]
                                 tau: the LMPC torque after the trust region, saturated;
                                 next_law_state already records tau as the applied torque;
                                 trust = [fallback (1 - alpha, 0..1), joints_clamped (0..N)]

Trust region (schema 2, manifest field ``trust_region``; the rule the runtime's safety supervisor
uses, applied inside the graph and reproduced in numpy by ``trust_filter``)::

    g = guard features (trust_region.features, GUARD_FEATURES: the full state (q, e, qd, e_dot,
        qdd_d, tau_fb), whatever the emulator's own inputs), r = emulator output
    residual target: tau_L = tau_fb + r;  absolute target: r = tau_L_raw - tau_fb
    d     = max_j max(low_j - g_j, g_j - high_j, 0) / (high_j - low_j)    how far outside the box
    alpha = clip(1 - d / m, 0, 1),  m = box_margin     (1 inside the box, 0 beyond the margin)
    tau   = sat(tau_fb + alpha clip(r, -bound, bound))  (bound: residual_bound_nm)
    alpha = 0 is a full fallback to the feedback law; 0 < alpha < 1 a blend (continuous in the
    state, so the switch itself does not excite the arm).

``PolicyBundle.load`` refuses, with a one-line ``BundleError`` (exit code 2), a bundle whose
manifest is missing or unreadable, whose schema is unknown, whose files are missing or fail their
sha256, whose graph does not match the declared layout, or whose joint count, joint names or
control period differ from what the caller expects. Nothing is written.

Only numpy, onnxruntime and the standard library here (the runtime never imports models/torch).

    bundle = PolicyBundle.load(path, expected_joints=6, expected_period_s=1e-3)
    state = bundle.initial_state(q0)
    tau, tau_fb, state = bundle.step(q, qd, q_d, qd_d, qdd_d, state)   # one arm, (N,) arrays
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

SCHEMA = "hil-policy-bundle/2"
SUPPORTED_SCHEMAS = (SCHEMA,)
MANIFEST = "manifest.json"
INPUT_LAYOUT = ("q", "qd", "q_d", "qd_d", "qdd_d", "law_state")
OUTPUT_LAYOUT = ("tau", "tau_fb", "next_law_state", "trust")
TRUST_SIZE = 2  # [fallback = 1 - alpha, joints_clamped]
FEATURE_SETS = {"eq22": ("q", "e", "qd", "e_dot", "tau_fb"), "eq22+qdd_d": ("q", "e", "qd", "e_dot", "qdd_d", "tau_fb"),
                "ref": ("q_d", "qd_d", "qdd_d")}
GUARD_FEATURES = "eq22+qdd_d"  # what the trust box is over
TRUST_MIN_SPAN = 1e-9


class BundleError(ValueError):
    """A bundle the runtime refuses; the message is one line naming the file."""

    exit_code = 2


@dataclass(frozen=True)
class Slot:
    name: str
    start: int
    size: int

    @property
    def slice(self) -> slice:
        return slice(self.start, self.start + self.size)


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _layout(raw: Any, expected: tuple[str, ...], where: str) -> tuple[Slot, ...]:
    if not isinstance(raw, list) or [item.get("name") if isinstance(item, dict) else None for item in raw] != list(expected):
        raise BundleError(f"{where}: layout must list {', '.join(expected)} in that order")
    slots, start = [], 0
    for item in raw:
        size = item.get("size")
        if not isinstance(size, int) or size < 0:
            raise BundleError(f"{where}: layout entry '{item['name']}' needs an integer size >= 0")
        slots.append(Slot(item["name"], start, size))
        start += size
    return tuple(slots)


class PolicyBundle:
    """A verified bundle with one onnxruntime session (1 intra-op thread) and preallocated buffers."""

    def __init__(self, path: Path, manifest: dict[str, Any], session: Any, inputs: tuple[Slot, ...],
                 outputs: tuple[Slot, ...]) -> None:  # fmt: skip
        self.path, self.manifest, self.session = path, manifest, session
        self.inputs = {s.name: s for s in inputs}
        self.outputs = {s.name: s for s in outputs}
        self.n_joints = int(manifest["robot"]["n_joints"])
        self.joint_names = tuple(manifest["robot"]["joint_names"])
        self.period_s = float(manifest["control_period_s"])
        self.law_name = str(manifest["law"]["name"])
        self.state_size = int(manifest["law"]["state_size"])
        self.torque_limit_nm = np.asarray(manifest["limits"]["torque_nm"], float)
        init = manifest["law"]["initial_state"]
        self._init_constant = np.asarray(init["constant"], float).reshape(self.state_size)
        self._init_gain = np.asarray(init["position_gain"], float).reshape(self.state_size, self.n_joints)
        self.input_width = sum(s.size for s in inputs)
        self.output_width = sum(s.size for s in outputs)
        self._input_name = manifest["graph"]["input"]["name"]
        self._output_name = manifest["graph"]["output"]["name"]
        # Single-arm fast path: the input row and the output row live in fixed buffers bound once.
        self._x = np.zeros((1, self.input_width))
        self._y = np.zeros((1, self.output_width))
        self._binding = self._bind(self._x, self._y)

    # --- loading ------------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path, expected_joints: int | None = None, expected_period_s: float | None = None,
             expected_joint_names: tuple[str, ...] | list[str] | None = None,
             expected_urdf_sha256: str | None = None, intra_op_threads: int = 1) -> PolicyBundle:  # fmt: skip
        """Verify and open the bundle at ``path``; raise BundleError (one line) on any mismatch."""
        path = Path(path)
        manifest_path = path / MANIFEST
        if not path.is_dir():
            raise BundleError(f"bundle {path}: not a directory")
        if not manifest_path.is_file():
            raise BundleError(f"bundle {manifest_path}: missing file")
        try:
            manifest = json.loads(manifest_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise BundleError(f"bundle {manifest_path}: unreadable JSON ({str(exc).splitlines()[0]})") from None
        if not isinstance(manifest, dict):
            raise BundleError(f"bundle {manifest_path}: not a JSON object")
        schema = manifest.get("schema")
        if schema not in SUPPORTED_SCHEMAS:
            raise BundleError(f"bundle {manifest_path}: unknown schema {schema!r} (supported: {', '.join(SUPPORTED_SCHEMAS)})")
        try:
            files = dict(manifest["files"])
            robot = manifest["robot"]
            n_joints = int(robot["n_joints"])
            joint_names = list(robot["joint_names"])
            period_s = float(manifest["control_period_s"])
            graph = manifest["graph"]
            graph_file = str(graph["file"])
            state_size = int(manifest["law"]["state_size"])
            torque = manifest["limits"]["torque_nm"]
            manifest["law"]["initial_state"]["constant"], manifest["law"]["initial_state"]["position_gain"]
            feature_set = str(manifest["emulator"]["feature_set"])
            bool(manifest["emulator"]["residual"])
            trust = manifest["trust_region"]
        except (KeyError, TypeError, ValueError) as exc:
            raise BundleError(f"bundle {manifest_path}: missing or malformed field {exc}") from None
        if len(joint_names) != n_joints or len(torque) != n_joints:
            raise BundleError(f"bundle {manifest_path}: n_joints {n_joints} disagrees with joint_names/limits")
        if feature_set not in FEATURE_SETS:
            raise BundleError(f"bundle {manifest_path}: unknown emulator feature_set {feature_set!r} (known: {', '.join(FEATURE_SETS)})")
        if trust is not None:
            width = len(FEATURE_SETS[GUARD_FEATURES]) * n_joints
            try:
                low, high = np.asarray(trust["feature_low"], float), np.asarray(trust["feature_high"], float)
                bound = trust["residual_bound_nm"]
                ok = (low.shape == high.shape == (width,) and float(trust["box_margin"]) >= 0
                      and (bound is None or np.asarray(bound, float).shape == (n_joints,)))  # fmt: skip
            except (KeyError, TypeError, ValueError):
                ok = False
            if not ok:
                raise BundleError(f"bundle {manifest_path}: trust_region needs feature_low/high ({width}), box_margin >= 0, "
                                  f"residual_bound_nm ({n_joints} or null)")  # fmt: skip
        for name, digest in sorted(files.items()):
            file = path / name
            if not file.is_file():
                raise BundleError(f"bundle {file}: missing file")
            actual = sha256_file(file)
            if actual != digest:
                raise BundleError(f"bundle {file}: sha256 mismatch (manifest {str(digest)[:12]}…, file {actual[:12]}…)")
        if graph_file not in files:
            raise BundleError(f"bundle {manifest_path}: graph file '{graph_file}' is not listed with a sha256")
        if expected_joints is not None and n_joints != expected_joints:
            raise BundleError(f"bundle {manifest_path}: {n_joints} joints, the config has {expected_joints}")
        if expected_joint_names is not None and list(expected_joint_names) != joint_names:
            raise BundleError(f"bundle {manifest_path}: joint order {joint_names} differs from the config's {list(expected_joint_names)}")
        if expected_period_s is not None and not math.isclose(period_s, expected_period_s, rel_tol=1e-9, abs_tol=1e-12):
            raise BundleError(f"bundle {manifest_path}: control period {period_s} s, the config has {expected_period_s} s")
        if expected_urdf_sha256 is not None and robot.get("urdf_sha256") != expected_urdf_sha256:
            raise BundleError(f"bundle {manifest_path}: robot URDF sha256 differs from the config's robot")
        n = n_joints
        inputs = _layout(graph["input"].get("layout"), INPUT_LAYOUT, f"bundle {manifest_path} graph input")
        outputs = _layout(graph["output"].get("layout"), OUTPUT_LAYOUT, f"bundle {manifest_path} graph output")
        sizes = {s.name: s.size for s in (*inputs, *outputs)}
        want = {"q": n, "qd": n, "q_d": n, "qd_d": n, "qdd_d": n, "law_state": state_size, "tau": n, "tau_fb": n,
                "next_law_state": state_size, "trust": TRUST_SIZE}  # fmt: skip
        if sizes != want:
            raise BundleError(f"bundle {manifest_path}: layout sizes {sizes} do not fit {n} joints and state {state_size}")
        session = _open_session(path / graph_file, intra_op_threads)
        width_in, width_out = sum(s.size for s in inputs), sum(s.size for s in outputs)
        got_in, got_out = session.get_inputs(), session.get_outputs()
        if (len(got_in) != 1 or len(got_out) != 1 or got_in[0].name != graph["input"].get("name")
                or got_out[0].name != graph["output"].get("name") or got_in[0].shape[-1] != width_in
                or got_out[0].shape[-1] != width_out):  # fmt: skip
            raise BundleError(f"bundle {path / graph_file}: graph inputs/outputs do not match the manifest layout "
                              f"({width_in} -> {width_out})")  # fmt: skip
        return cls(path, manifest, session, inputs, outputs)

    # --- running ------------------------------------------------------------------------------
    def _bind(self, x: np.ndarray, y: np.ndarray) -> Any:
        import onnxruntime as ort

        binding = self.session.io_binding()
        binding.bind_ortvalue_input(self._input_name, ort.OrtValue.ortvalue_from_numpy(x))
        binding.bind_ortvalue_output(self._output_name, ort.OrtValue.ortvalue_from_numpy(y))
        return binding

    def initial_state(self, q0: np.ndarray) -> np.ndarray:
        """The law's state at the start of a run from positions q0: (N,) -> (S,), (B, N) -> (B, S)."""
        q0 = np.asarray(q0, float)
        return self._init_constant + q0 @ self._init_gain.T

    def step(self, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray,
             law_state: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        """One arm, one period: (tau (N,), tau_fb (N,), next_law_state (S,)), views of a reused buffer.

        Copy the results if you keep them past the next call.
        """
        x, n = self._x[0], self.n_joints
        x[0:n] = q
        x[n : 2 * n] = qd
        x[2 * n : 3 * n] = q_d
        x[3 * n : 4 * n] = qd_d
        x[4 * n : 5 * n] = qdd_d
        x[5 * n :] = law_state
        self.session.run_with_iobinding(self._binding)
        y = self._y[0]
        return y[:n], y[n : 2 * n], y[2 * n : 2 * n + self.state_size]

    @property
    def last_trust(self) -> np.ndarray:
        """[fallback (1 - alpha), joints_clamped] of the last ``step`` (a view of the output row)."""
        return self._y[0, 2 * self.n_joints + self.state_size :]

    def step_batch(self, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray,
                   law_state: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        """B arms at once ((B, N) arrays, law_state (B, S)): new arrays (tau, tau_fb, next_law_state).

        ``last_trust_batch`` holds the (B, 2) trust output of the call.
        """
        x = np.concatenate([np.asarray(a, float).reshape(np.shape(q)[0], -1) for a in (q, qd, q_d, qd_d, qdd_d, law_state)], 1)
        y = self.session.run([self._output_name], {self._input_name: x})[0]
        n, s = self.n_joints, self.state_size
        self.last_trust_batch = y[:, 2 * n + s :]
        return y[:, :n], y[:, n : 2 * n], y[:, 2 * n : 2 * n + s]

    def describe(self) -> dict[str, Any]:
        """What telemetry's bundle-info queryable publishes."""
        return {"path": str(self.path), "schema": self.manifest["schema"], "law": self.law_name,
                "robot": self.manifest["robot"]["name"], "n_joints": self.n_joints, "period_s": self.period_s,
                "files": self.manifest["files"], "validation": self.manifest.get("validation", {}),
                "trust_region": self.manifest.get("trust_region")}  # fmt: skip


def emulator_features(feature_set: str, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray,
                      qdd_d: np.ndarray, tau_fb: np.ndarray) -> np.ndarray:  # fmt: skip
    """The emulator input s of ``feature_set`` (FEATURE_SETS), last axis."""
    parts = {"q": q, "e": q_d - q, "qd": qd, "e_dot": qd_d - qd, "q_d": q_d, "qd_d": qd_d, "qdd_d": qdd_d, "tau_fb": tau_fb}
    return np.concatenate([np.asarray(parts[k], float) for k in FEATURE_SETS[feature_set]], axis=-1)


def trust_filter(manifest: dict[str, Any], s: np.ndarray, r: np.ndarray, tau_fb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The trust-region rule (module docstring) in numpy: (tau (B, N), trust (B, 2)) from the guard
    features s (B, F) (``emulator_features(GUARD_FEATURES, ...)``), the emulator's residual r (B, N)
    (tau_L_raw - tau_fb for an absolute-target emulator) and tau_fb (B, N). The graph applies the
    same rule; the safety supervisor can re-check with it."""
    limit = np.asarray(manifest["limits"]["torque_nm"], float)
    s, r, tau_fb = np.atleast_2d(s), np.atleast_2d(r), np.atleast_2d(tau_fb)
    trust = manifest.get("trust_region")
    alpha = np.ones(s.shape[0])
    clamped = np.zeros(s.shape[0])
    if trust is not None:
        low, high = np.asarray(trust["feature_low"], float), np.asarray(trust["feature_high"], float)
        span = np.maximum(high - low, TRUST_MIN_SPAN)
        d = np.max(np.maximum(np.maximum(low - s, s - high), 0.0) / span, axis=1)
        alpha = np.clip(1.0 - d / max(float(trust["box_margin"]), 1e-12), 0.0, 1.0)
        if trust.get("residual_bound_nm") is not None:
            bound = np.asarray(trust["residual_bound_nm"], float)
            clamped = np.sum(np.abs(r) > bound, axis=1).astype(float)
            r = np.clip(r, -bound, bound)
    tau = np.clip(tau_fb + alpha[:, None] * r, -limit, limit)
    return tau, np.stack([1.0 - alpha, np.where(alpha > 0, clamped, 0.0)], 1)


def _open_session(file: Path, intra_op_threads: int) -> Any:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = intra_op_threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.log_severity_level = 3
    try:
        return ort.InferenceSession(str(file), sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own untyped errors on bad graphs
        reason = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
        raise BundleError(f"bundle {file}: onnxruntime cannot load the graph ({reason})") from None
