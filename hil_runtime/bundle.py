"""Policy bundles: load, verify and step the exported feedback law + torque emulator.

A bundle is a directory written by ``models.lmpc.bundle_export`` (docs/architecture.md, contract 1)::

    <bundle>/manifest.json   schema, robot + URDF sha256, joints, period, limits, law, layout,
                             training provenance, validation error, sha256 of every file
    <bundle>/policy.onnx     one fused graph: x (B, 5N+S[+N]) -> y (B, 2N+S+2), float64
                             x = [q, qd, q_d, qd_d, qdd_d, law_state(, tau_prev)]
                                 tau_prev (optional, declared as the input layout's last slot): the
                                 torque commanded last period; such a graph steps from it within
                                 the rate bound (docs/lmpc.md §11). Its caller keeps it in
                                 ``previous_torque_nm`` (the runtime's Controller: commit / reset)
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
manifest is missing, unreadable or fails the schema (``hil_runtime.bundle_schema``, shared with the
writer), whose files are missing or fail their sha256, whose graph does not match the declared
layout, whose joint count, joint names, control period or URDF sha256 differ from what the caller
expects, or whose graph does not behave as its manifest says: it must reproduce the recorded probe
outputs (a graph of another law under a fixed-up sha256 fails here), saturate at
``limits.torque_nm`` and keep its residual within ``trust_region.residual_bound_nm`` wherever the
probes exercise them (:mod:`hil_runtime.bundle_probes`, which also makes the probe rows the
writer records). Nothing is written. The trust-region rule in numpy is :mod:`hil_runtime.trust_region`.

``step`` only produces: a non-finite graph output is the runtime's safety supervisor's to handle
(:func:`hil_runtime.supervisor.policy_torque`, the one rule: the law's torque instead, or FAULT
``policy_nonfinite``). ``step_batch`` (offline runs, no supervisor) applies the same rule per arm:
the law's torque, saturated, as a full fallback (``nonfinite_fallbacks``); an arm with nothing
usable stays non-finite (``nonfinite_refusals``), so the run records its divergence.

Only numpy, onnxruntime and the standard library here (the runtime never imports models/torch).

    bundle = PolicyBundle.load(path, expected_joints=6, expected_period_s=1e-3)
    state = bundle.initial_state(q0)
    tau, tau_fb, state = bundle.step(q, qd, q_d, qd_d, qdd_d, state)   # one arm, (N,) arrays
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from drivers.joint_bus import clip_torque
from drivers.strict_input import loads_json_unique
from hil_runtime.bundle_probes import (
    DEFAULT_ENCODER_NOISE_RAD,
    GraphCheckError,
    check_graph,
    check_sensing,
    probe_section,
    tolerated_encoder_noise_rad,
    torque_rate_nm_s,
)
from hil_runtime.bundle_schema import MANIFEST, SUPPORTED_SCHEMAS, Manifest, format_manifest_error
from hil_runtime.bundle_security import (
    MAX_GRAPH_BYTES,
    MAX_MANIFEST_BYTES,
    PROBE_RUN_TIMEOUT_S,
    BundleSecurityError,
    check_bundle_id,
    check_graph_bytes,
    check_signature,
    member_file,
    read_bounded,
)
from hil_runtime.supervisor import policy_torque

__all__ = ["DEFAULT_ENCODER_NOISE_RAD", "BundleError", "PolicyBundle", "record_probes", "sha256_file"]


class BundleError(ValueError):
    """A bundle the runtime refuses; the message is one line naming the file."""

    exit_code = 2


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


class PolicyBundle:
    """A verified bundle with one onnxruntime session (1 intra-op thread) and preallocated buffers."""

    def __init__(self, path: Path, manifest: Manifest, session: Any) -> None:
        self.path, self.manifest, self.session = path, manifest, session
        self.layout = manifest.layout
        self.n_joints = manifest.robot.n_joints
        self.joint_names = tuple(manifest.robot.joint_names)
        self.period_s = manifest.period_s
        self.law_name = manifest.law.name
        self.state_size = manifest.law.state_size
        self.torque_limit_nm = np.asarray(manifest.limits.torque_nm, float)
        self.torque_rate_nm_s = torque_rate_nm_s(manifest)  # the robot's torque-rate bound (bundle_probes)
        trust = manifest.trust_region
        bound = None if trust is None else trust.residual_bound_nm
        self.residual_bound_nm = None if bound is None else np.asarray(bound, float)
        self.saturation_checked = np.zeros(self.n_joints, bool)  # joints whose graph saturation was observed
        self._torque_limit_list = self.torque_limit_nm.tolist()
        # step_batch's arms (offline) whose graph torque was non-finite: the law's torque instead /
        # nothing usable (the runtime's supervisor counts its own: law_substitutions)
        self.nonfinite_fallbacks = 0
        self.nonfinite_refusals = 0
        init = manifest.law.initial_state
        self._init_constant = np.asarray(init.constant, float).reshape(self.state_size)
        self._init_gain = np.asarray(init.position_gain, float).reshape(self.state_size, self.n_joints)
        self.input_width = self.layout.input_width
        self.output_width = self.layout.output_width
        self._input_name = manifest.graph.input.name
        self._output_name = manifest.graph.output.name
        # Single-arm fast path: the input row and the output row live in fixed buffers bound once.
        self._x = np.zeros((1, self.input_width))
        self._y = np.zeros((1, self.output_width))
        self._binding = self._bind(self._x, self._y)
        # step's Python is ~10 % of a call: the row views, the output views it returns and the bound
        # run are made once here, not per cycle (step returns these same view objects every call)
        n = self.n_joints
        self._x_row: np.ndarray = self._x[0]
        self._y_row: np.ndarray = self._y[0]
        tau, tau_fb, next_state, trust_view = self.layout.split(self._y_row)
        self._step_out: tuple[np.ndarray, np.ndarray, np.ndarray] = (tau, tau_fb, next_state)
        # tau_prev's place in the bound input row (None: the graph does not read it): the caller writes
        # the torque it commanded here (Controller.commit), and the held torque on activation (reset)
        self.takes_previous_torque = manifest.takes_previous_torque
        self._law_state_row: np.ndarray = self._x_row[5 * n : 5 * n + self.state_size]
        self.previous_torque_nm: np.ndarray | None = (
            self._x_row[self.layout.previous_torque_columns] if self.takes_previous_torque else None
        )
        self._trust_view: np.ndarray = trust_view
        # (tau, tau_fb) of the last step as one (2, 1, N) view: one copy gives both as (1, N) rows
        self.last_torques: np.ndarray = self._y_row[: 2 * n].reshape(2, 1, n)
        self._run_bound, self._binding_native = _native_run(session, self._binding)

    # --- loading ------------------------------------------------------------------------------
    @classmethod
    def load(
        cls,
        path: str | Path,
        expected_joints: int | None = None,
        expected_period_s: float | None = None,
        expected_joint_names: tuple[str, ...] | list[str] | None = None,
        expected_urdf_sha256: str | None = None,
        intra_op_threads: int = 1,
        check_behaviour: bool = True,
        trusted_keys: Sequence[Any] = (),
    ) -> PolicyBundle:
        """Verify and open the bundle at ``path``; raise BundleError (one line) on any mismatch.

        ``check_behaviour=False`` skips the probe checks and the manifest's ``bundle_id``: only for
        the writer while it records them. ``trusted_keys`` (Ed25519 public keys): when given, the
        manifest must carry a signature by one of them (:mod:`hil_runtime.bundle_security`).
        """
        try:
            return cls._load(
                Path(path),
                expected_joints,
                expected_period_s,
                expected_joint_names,
                expected_urdf_sha256,
                intra_op_threads,
                check_behaviour,
                trusted_keys,
            )
        except BundleSecurityError as exc:
            raise BundleError(f"bundle {exc}") from None

    @classmethod
    def _load(
        cls,
        path: Path,
        expected_joints: int | None,
        expected_period_s: float | None,
        expected_joint_names: tuple[str, ...] | list[str] | None,
        expected_urdf_sha256: str | None,
        intra_op_threads: int,
        check_behaviour: bool,
        trusted_keys: Sequence[Any],
    ) -> PolicyBundle:
        manifest_path = path / MANIFEST
        if not path.exists():
            raise BundleError(f"bundle {path}: no such directory")
        if not path.is_dir():
            raise BundleError(f"bundle {path}: not a directory")
        if not manifest_path.is_file():
            raise BundleError(f"bundle {path}: no {MANIFEST} in this directory (missing file {manifest_path})")
        member_file(path, MANIFEST, str(manifest_path))  # not a symlink out of the bundle
        try:
            raw = loads_json_unique(read_bounded(manifest_path, MAX_MANIFEST_BYTES, "manifest").decode("utf-8"))
        except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
            raise BundleError(f"bundle {manifest_path}: unreadable JSON ({str(exc).splitlines()[0]})") from None
        if not isinstance(raw, dict):
            raise BundleError(f"bundle {manifest_path}: not a JSON object")
        schema = raw.get("schema")
        if schema not in SUPPORTED_SCHEMAS:
            raise BundleError(
                f"bundle {manifest_path}: unknown schema {schema!r} (supported: {', '.join(SUPPORTED_SCHEMAS)})"
            )
        try:
            parsed = Manifest.model_validate(raw)
        except ValidationError as exc:
            raise BundleError(format_manifest_error(f"bundle {manifest_path}", exc)) from None
        if check_behaviour and parsed.probes is None:
            raise BundleError(
                f"bundle {manifest_path}: probes: missing (a bundle records probe inputs and outputs; "
                "re-export it with `hil pipeline`)"
            )
        n_joints, joint_names = parsed.robot.n_joints, list(parsed.robot.joint_names)
        period_s, graph_file = parsed.period_s, parsed.graph.file
        graph_bytes = b""
        for name, digest in sorted(parsed.files.items()):
            file = member_file(path, name, f"{manifest_path}: files")
            if name == graph_file:  # hashed from the bytes onnxruntime is given: nothing swapped between
                graph_bytes = read_bounded(file, MAX_GRAPH_BYTES, "graph")
                actual = hashlib.sha256(graph_bytes).hexdigest()
            else:
                actual = sha256_file(file)
            if actual != digest:
                raise BundleError(f"bundle {file}: sha256 mismatch (manifest {str(digest)[:12]}…, file {actual[:12]}…)")
        if expected_joints is not None and n_joints != expected_joints:
            raise BundleError(f"bundle {manifest_path}: {n_joints} joints, the config has {expected_joints}")
        if expected_joint_names is not None and list(expected_joint_names) != joint_names:
            raise BundleError(
                f"bundle {manifest_path}: joint order {joint_names} differs from the config's "
                f"{list(expected_joint_names)}"
            )
        if expected_period_s is not None and not math.isclose(period_s, expected_period_s, rel_tol=1e-9, abs_tol=1e-12):
            raise BundleError(
                f"bundle {manifest_path}: control period {period_s} s, the config has {expected_period_s} s"
            )
        if expected_urdf_sha256 is not None and parsed.robot.urdf_sha256 != expected_urdf_sha256:
            raise BundleError(
                f"bundle {manifest_path}: robot.urdf_sha256 {parsed.robot.urdf_sha256[:12]}… differs from "
                f"the robot's URDF ({expected_urdf_sha256[:12]}…): exported for another robot description"
            )
        check_graph_bytes(graph_bytes, path / graph_file)  # operators, external data: before onnxruntime
        session = _open_session(graph_bytes, path / graph_file, intra_op_threads)
        width_in, width_out = parsed.layout.input_width, parsed.layout.output_width
        got_in, got_out = session.get_inputs(), session.get_outputs()
        if (
            len(got_in) != 1
            or len(got_out) != 1
            or got_in[0].name != parsed.graph.input.name
            or got_out[0].name != parsed.graph.output.name
            or got_in[0].shape[-1] != width_in
            or got_out[0].shape[-1] != width_out
        ):
            raise BundleError(
                f"bundle {path / graph_file}: graph inputs/outputs do not match the manifest layout "
                f"({width_in} -> {width_out})"
            )
        bundle = cls(path, parsed, session)
        if check_behaviour:
            try:
                bundle.saturation_checked = check_graph(parsed, bundle.run_rows, manifest_path)
            except GraphCheckError as exc:
                raise BundleError(str(exc)) from None
            bundle_id = check_bundle_id(raw, str(manifest_path))
            if trusted_keys:
                check_signature(raw, bundle_id, trusted_keys, str(manifest_path))
        return bundle

    # --- behavioural checks -------------------------------------------------------------------
    def check_sensing(
        self,
        encoder_noise_rad: float,
        velocity_noise_rad_s: float | None = None,
        velocity_filter_hz: float | None = None,
    ) -> np.ndarray:
        """Refuse (BundleError, one line) a graph that turns this much measurement noise (RMS; velocity None:
        the position's differenced over one period; behind the velocity filter, if any) into torque steps beyond
        the robot's rate bound per period; return the predicted steps per joint, N m
        (hil_runtime.bundle_probes.check_sensing)."""
        try:
            return check_sensing(
                self.manifest,
                self.run_rows,
                self.path / MANIFEST,
                encoder_noise_rad,
                velocity_noise_rad_s,
                velocity_filter_hz,
            )
        except GraphCheckError as exc:
            raise BundleError(str(exc)) from None

    def tolerated_encoder_noise_rad(self) -> float:
        """The largest encoder noise (RMS, velocity differenced) :meth:`check_sensing` accepts; inf for a graph
        that reads tau_prev."""
        return tolerated_encoder_noise_rad(self.manifest, self.run_rows)

    def run_rows(self, x: np.ndarray) -> np.ndarray:
        """Output rows for input rows (B, 5N + S), as the graph gives them (no fallback); a run
        longer than PROBE_RUN_TIMEOUT_S is stopped (BundleError). For checks, not the loop."""
        import onnxruntime as ort

        # A load-time bound: onnxruntime stops a run whose RunOptions.terminate is set (from a timer)
        options = ort.RunOptions()
        timer = threading.Timer(PROBE_RUN_TIMEOUT_S, lambda: setattr(options, "terminate", True))
        timer.daemon = True
        timer.start()
        try:
            rows: np.ndarray = self.session.run(
                [self._output_name], {self._input_name: np.ascontiguousarray(x, np.float64)}, options
            )[0]
            return rows
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own untyped errors
            if options.terminate:
                raise BundleError(
                    f"bundle {self.path}: the graph ran longer than {PROBE_RUN_TIMEOUT_S:g} s on probe inputs"
                ) from None
            raise BundleError(
                f"bundle {self.path}: the graph fails on probe inputs ({str(exc).splitlines()[0][:160]})"
            ) from None
        finally:
            timer.cancel()

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
        state: np.ndarray = self._init_constant + q0 @ self._init_gain.T
        return state

    def step(
        self, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray, law_state: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One arm, one period: (tau (N,), tau_fb (N,), next_law_state (S,)), views of a reused buffer.

        The same view objects every call: copy the results if you keep them past the next call.
        Unchecked: a non-finite output is the caller's (the runtime's supervisor, module docstring).
        """
        x, n = self._x_row, self.n_joints
        x[0:n] = q
        x[n : 2 * n] = qd
        x[2 * n : 3 * n] = q_d
        x[3 * n : 4 * n] = qd_d
        x[4 * n : 5 * n] = qdd_d
        self._law_state_row[:] = law_state  # tau_prev (if read) stays as the caller set it
        self._run_bound(self._binding_native, None)
        return self._step_out

    @property
    def last_trust(self) -> np.ndarray:
        """[fallback (1 - alpha), joints_clamped] of the last ``step`` (a view of the output row)."""
        return self._trust_view

    def step_batch(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        q_d: np.ndarray,
        qd_d: np.ndarray,
        qdd_d: np.ndarray,
        law_state: np.ndarray,
        previous_torque_nm: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """B arms at once ((B, N) arrays, law_state (B, S)): new arrays (tau, tau_fb, next_law_state).

        ``previous_torque_nm`` (B, N): each arm's torque commanded last period, required by a graph that
        reads it (``takes_previous_torque``), ignored otherwise. ``last_trust_batch`` holds the (B, 2)
        trust output of the call.
        """
        rows = [q, qd, q_d, qd_d, qdd_d, law_state]
        if self.takes_previous_torque:
            if previous_torque_nm is None:
                raise ValueError(f"bundle {self.path}: the graph reads tau_prev; step_batch needs previous_torque_nm")
            rows.append(previous_torque_nm)
        x = np.concatenate([np.asarray(a, float).reshape(np.shape(q)[0], -1) for a in rows], 1)
        y = self.session.run([self._output_name], {self._input_name: x})[0]
        tau, tau_fb, next_state, self.last_trust_batch = self.layout.split(y)
        if not np.isfinite(y).all():
            for row in np.flatnonzero(~np.isfinite(y).all(axis=1)):
                self._law_fallback(tau[row], tau_fb[row], next_state[row], self.last_trust_batch[row])
        return tau, tau_fb, next_state

    def _law_fallback(self, tau: np.ndarray, tau_fb: np.ndarray, next_state: np.ndarray, trust: np.ndarray) -> None:
        """The supervisor's non-finite rule on one arm of an offline batch (no supervisor there):
        the law's torque, saturated, reported as a full fallback; an arm with nothing usable stays
        non-finite, so offline runs record its divergence."""
        usable = policy_torque(tau, tau_fb, next_state)
        if usable is None:
            self.nonfinite_refusals += 1
        elif usable[0] is not tau:
            limit = self._torque_limit_list
            clip_torque(tau_fb, usable[1], limit, limit, tau)
            trust[:] = (1.0, 0.0)  # a full fallback to the law, as the trust region reports it
            self.nonfinite_fallbacks += 1

    def describe(self) -> dict[str, Any]:
        """What telemetry's bundle-info queryable publishes."""
        trust = self.manifest.trust_region
        return {
            "path": str(self.path),
            "schema": self.manifest.schema_id,
            "law": self.law_name,
            "robot": self.manifest.robot.name,
            "n_joints": self.n_joints,
            "period_s": self.period_s,
            "files": dict(self.manifest.files),
            "validation": self.manifest.validation,
            "trust_region": None if trust is None else trust.model_dump(),
            "bundle_id": self.manifest.bundle_id,
        }


def _native_run(session: Any, binding: Any) -> tuple[Any, Any]:
    """(run, binding) for ``run(binding, None)``: onnxruntime's C++ call when the Python wrapper exposes it.

    InferenceSession.run_with_iobinding (1.32) adds WebGPU graph-capture bookkeeping around the C++
    call, ~0.5 us a cycle that the CPU provider never needs; the public call when the names moved."""
    native_session, native_binding = getattr(session, "_sess", None), getattr(binding, "_iobinding", None)
    if native_session is None or native_binding is None or not hasattr(native_session, "run_with_iobinding"):
        return session.run_with_iobinding, binding
    return native_session.run_with_iobinding, native_binding


def _open_session(graph: bytes, file: Path, intra_op_threads: int) -> Any:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = intra_op_threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.log_severity_level = 3
    try:
        # From the checked bytes, not the path: onnxruntime reads no other file (external data has no
        # directory to resolve against) and the file cannot be swapped after it was hashed.
        return ort.InferenceSession(graph, sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own untyped errors on bad graphs
        reason = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
        raise BundleError(f"bundle {file}: onnxruntime cannot load the graph ({reason})") from None


def record_probes(path: str | Path, count: int = 12) -> dict[str, Any]:
    """The ``probes`` section for the bundle at ``path`` (the writer's step; graph and files final)."""
    bundle = PolicyBundle.load(path, check_behaviour=False)
    try:
        return probe_section(bundle.manifest, bundle.run_rows, str(path), count)
    except GraphCheckError as exc:
        raise BundleError(str(exc)) from None
