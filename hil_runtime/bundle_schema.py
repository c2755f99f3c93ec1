"""The policy-bundle contract as one schema: the writer (models.lmpc.bundle_export) validates the
manifest it writes with it, the loader (hil_runtime.bundle) the manifest it reads.

Light: pydantic and the standard library. The layout of the fused graph and the trust-region rule
are documented in hil_runtime/bundle.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from hil_runtime.bundle_security import MAX_PROBE_ROWS

if TYPE_CHECKING:  # the layout's split works on numpy rows; the schema itself needs no numpy
    import numpy as np

SCHEMA = "hil-policy-bundle/3"  # 3: the control period is period_s (2 called it control_period_s)
SUPPORTED_SCHEMAS = (SCHEMA,)
MANIFEST = "manifest.json"
INPUT_LAYOUT = ("q", "qd", "q_d", "qd_d", "qdd_d", "law_state")
# An optional last input slot (N): the torque commanded last period (after the supervisor), for a graph that
# steps from it within the rate bound (docs/lmpc.md §11). A bundle without it reads as before.
PREVIOUS_TORQUE = "tau_prev"
OUTPUT_LAYOUT = ("tau", "tau_fb", "next_law_state", "trust")
TRUST_SIZE = 2  # [fallback = 1 - alpha, joints_clamped]
FEATURE_SETS = {
    "eq22": ("q", "e", "qd", "e_dot", "tau_fb"),
    "eq22+qdd_d": ("q", "e", "qd", "e_dot", "qdd_d", "tau_fb"),
    "ref": ("q_d", "qd_d", "qdd_d"),
}
GUARD_FEATURES = "eq22+qdd_d"  # what the trust box is over
TRUST_MIN_SPAN = 1e-9
PROBE_ATOL_MAX = 1e-3  # a manifest cannot loosen the behavioural check beyond this (N m)

FeatureSet = Literal["eq22", "eq22+qdd_d", "ref"]


@dataclass(frozen=True)
class GraphLayout:
    """The fused graph's row layout (INPUT_LAYOUT, OUTPUT_LAYOUT) for N joints and a law state of S:
    x = [q, qd, q_d, qd_d, qdd_d, law_state] (5N + S), + [tau_prev] (N) when ``previous_torque``,
    y = [tau, tau_fb, next_law_state, trust] (2N + S + TRUST_SIZE). The one place the offsets are written."""

    n_joints: int
    state_size: int
    previous_torque: bool = False

    @property
    def input_width(self) -> int:
        return (6 if self.previous_torque else 5) * self.n_joints + self.state_size

    @property
    def previous_torque_columns(self) -> slice:
        """Where tau_prev sits in an input row (an empty slice without it)."""
        start = 5 * self.n_joints + self.state_size
        return slice(start, self.input_width)

    @property
    def output_width(self) -> int:
        return 2 * self.n_joints + self.state_size + TRUST_SIZE

    def split(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(tau, tau_fb, next_law_state, trust): views along the last axis of an output row or rows."""
        n, s = self.n_joints, self.state_size
        return y[..., :n], y[..., n : 2 * n], y[..., 2 * n : 2 * n + s], y[..., 2 * n + s :]

    def output_slot(self, column: int) -> tuple[str, int]:
        """(slot name, index inside it) of an output column, for messages."""
        start = 0
        for name, size in zip(OUTPUT_LAYOUT, self._output_sizes(), strict=True):
            if column < start + size:
                return name, column - start
            start += size
        raise IndexError(column)

    def _output_sizes(self) -> tuple[int, int, int, int]:
        return self.n_joints, self.n_joints, self.state_size, TRUST_SIZE


class _Strict(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class _Open(BaseModel):
    """A section that may carry descriptive extras (notes, provenance) besides the checked fields."""

    model_config = ConfigDict(frozen=True, extra="allow", allow_inf_nan=False)


class Slot(_Strict):
    name: str
    size: int = Field(ge=0)


class Port(_Strict):
    name: str
    layout: list[Slot]


class Graph(_Strict):
    file: str = Field(min_length=1)
    opset: int = Field(ge=1)
    dtype: Literal["float64"]
    input: Port
    output: Port
    fused: str = ""


class Robot(_Strict):
    name: str
    urdf_file: str
    urdf_sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    n_joints: int = Field(ge=1)
    joint_names: list[str]


class Limits(_Strict):
    position_rad: list[float]  # symmetric bound |q| <= this (the conservative one of an asymmetric range)
    velocity_rad_s: list[float]
    torque_nm: list[float]
    # An arm whose range is not symmetric about 0 (the Panda's elbow: [-3.07, -0.07] rad) gives it
    # here; the runtime's soft limits are then [lower, upper] instead of [-position, position].
    position_lower_rad: list[float] | None = None
    position_upper_rad: list[float] | None = None
    # The commanded torque's rate bound per joint (N·m/s; hil_runtime.rate_limit), the robot's at export.
    # Absent in a bundle written before it existed: the "scaled" rule it was made under.
    torque_rate_nm_s: list[float] | None = None


class InitialState(_Strict):
    constant: list[float]  # (S,)
    position_gain: list[list[float]]  # (S, N): initial_state(q0) = constant + gain q0


class Law(_Strict):
    name: str = Field(min_length=1)
    params: dict[str, Any]
    gain_set: str | None = None
    state_size: int = Field(ge=0)
    applied_torque_slice: tuple[int, int] | None = None
    initial_state: InitialState


class Emulator(_Open):
    feature_set: FeatureSet
    residual: bool


class TrustRegion(_Open):
    feature_low: list[float]
    feature_high: list[float]
    box_margin: float = Field(ge=0)
    residual_bound_nm: list[float] | None = None


class Probes(_Strict):
    """Graph inputs and the outputs the exporter's onnxruntime gave for them: the loader runs the
    graph on the inputs and compares (a graph swapped under a fixed-up sha256 fails here)."""

    inputs: list[list[float]] = Field(min_length=1, max_length=MAX_PROBE_ROWS)
    outputs: list[list[float]] = Field(min_length=1, max_length=MAX_PROBE_ROWS)
    atol: float = Field(1e-6, gt=0, le=PROBE_ATOL_MAX)  # N m, plus rtol 1e-6: another CPU's BLAS
    note: str = ""
    # per joint: the largest torque change (N m) 1 mrad of error on one measured joint position makes on the
    # probe rows (hil_runtime.bundle_probes.position_sensitivity); the loader refuses a graph above it
    position_sensitivity_nm_per_mrad: list[float] | None = None


class Signature(_Strict):
    key: str = Field(pattern=r"^[0-9a-f]{16}$")  # sha256 of the raw Ed25519 public key, first 16 hex
    ed25519: str = Field(max_length=200)  # base64 signature over the ASCII bundle_id


class Manifest(_Strict):
    schema_id: Literal["hil-policy-bundle/3"] = Field(alias="schema")
    robot: Robot
    period_s: float = Field(gt=0)
    limits: Limits
    law: Law
    graph: Graph
    emulator: Emulator
    trust_region: TrustRegion | None
    training: dict[str, Any]
    validation: dict[str, Any]
    created: str
    files: dict[str, str]
    probes: Probes | None = None  # required by the loader; absent only while the writer records them
    # sha256 of the canonical manifest without these two fields (hil_runtime.bundle_security)
    bundle_id: str | None = Field(None, pattern=r"^[0-9a-f]{64}$")
    signatures: list[Signature] = []

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False, populate_by_name=True)

    @property
    def layout(self) -> GraphLayout:
        return GraphLayout(self.robot.n_joints, self.law.state_size, self.takes_previous_torque)

    @property
    def takes_previous_torque(self) -> bool:
        """The graph reads tau_prev (the optional last input slot, PREVIOUS_TORQUE)."""
        return bool(self.graph.input.layout) and self.graph.input.layout[-1].name == PREVIOUS_TORQUE

    @model_validator(mode="after")
    def _consistent(self) -> Manifest:
        n, s = self.robot.n_joints, self.law.state_size
        if len(self.robot.joint_names) != n:
            raise ValueError(f"robot.joint_names has {len(self.robot.joint_names)} names for n_joints {n}")
        for name in (
            "position_rad",
            "velocity_rad_s",
            "torque_nm",
            "position_lower_rad",
            "position_upper_rad",
            "torque_rate_nm_s",
        ):
            values = getattr(self.limits, name)
            if values is not None and len(values) != n:
                raise ValueError(f"limits.{name} needs {n} values")
        lower, upper = self.limits.position_lower_rad, self.limits.position_upper_rad
        if (lower is None) != (upper is None):
            raise ValueError("limits.position_lower_rad and position_upper_rad go together")
        if lower is not None and upper is not None and any(not lo < hi for lo, hi in zip(lower, upper, strict=True)):
            raise ValueError("limits.position_lower_rad must be below position_upper_rad on every joint")
        if any(not t > 0 for t in self.limits.torque_nm):
            raise ValueError("limits.torque_nm must be positive")
        if any(not t > 0 for t in self.limits.torque_rate_nm_s or ()):
            raise ValueError("limits.torque_rate_nm_s must be positive")
        if self.takes_previous_torque and self.limits.torque_rate_nm_s is None:
            raise ValueError(f"limits.torque_rate_nm_s: required by a graph that reads {PREVIOUS_TORQUE}")
        init = self.law.initial_state
        if len(init.constant) != s or len(init.position_gain) != s or any(len(row) != n for row in init.position_gain):
            raise ValueError(f"law.initial_state needs constant ({s}) and position_gain ({s} x {n})")
        want_in = [(k, s if k == "law_state" else n) for k in INPUT_LAYOUT]
        want_out = [(k, {"next_law_state": s, "trust": TRUST_SIZE}.get(k, n)) for k in OUTPUT_LAYOUT]
        got_in = [(x.name, x.size) for x in self.graph.input.layout]
        if got_in not in (want_in, want_in + [(PREVIOUS_TORQUE, n)]):
            raise ValueError(f"graph.input.layout must be {want_in} (+ [('{PREVIOUS_TORQUE}', {n})])")
        if [(x.name, x.size) for x in self.graph.output.layout] != want_out:
            raise ValueError(f"graph.output.layout must be {want_out}")
        if self.graph.file not in self.files:
            raise ValueError(f"files: the graph file '{self.graph.file}' is not listed with a sha256")
        if self.trust_region is not None:
            width = len(FEATURE_SETS[GUARD_FEATURES]) * n
            trust = self.trust_region
            if len(trust.feature_low) != width or len(trust.feature_high) != width:
                raise ValueError(f"trust_region.feature_low/high need {width} values")
            if trust.residual_bound_nm is not None and (
                len(trust.residual_bound_nm) != n or any(not b >= 0 for b in trust.residual_bound_nm)
            ):
                raise ValueError(f"trust_region.residual_bound_nm needs {n} values >= 0 (or null)")
        if self.probes is not None:
            width_in, width_out = self.layout.input_width, self.layout.output_width
            if len(self.probes.inputs) != len(self.probes.outputs):
                raise ValueError("probes: inputs and outputs differ in count")
            if any(len(r) != width_in for r in self.probes.inputs) or any(
                len(r) != width_out for r in self.probes.outputs
            ):
                raise ValueError(f"probes: rows need {width_in} inputs and {width_out} outputs")
        return self


def format_manifest_error(where: str, exc: ValidationError) -> str:
    """One line: the manifest path, the first failing field, pydantic's reason."""
    errors = exc.errors()
    first = errors[0]
    loc = ".".join(str(part) for part in first["loc"])
    message = str(first["msg"]).removeprefix("Value error, ")  # our own cross-field checks name the field
    more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
    return f"{where}: {loc + ': ' if loc else ''}{message}{more}"
