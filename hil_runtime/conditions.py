"""Operating conditions as data: reference trajectories, disturbance and plant-model mismatch.

Light code (numpy, yaml, stdlib) owned by the runtime, which evaluates the reference every cycle;
``models.conditions`` re-exports it and adds what needs a robot model. The paper's five conditions
are ``hil_runtime/data/paper_conditions.yaml``; users write their own in the same format
(docs/conditions.md).

    conditions = load_conditions(None)               # the paper's five
    conditions = load_conditions("my_conditions.yaml")
    q_d, qd_d, qdd_d = conditions[0].reference(t_s)  # t_s scalar or (T,) -> (..., N)

Every refusal is a :class:`ConditionError`: one line naming the file and the field, exit code 2.
"""

from __future__ import annotations

import ast
import math
import operator
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, Self

import numpy as np

from drivers.config import read_yaml_config

if TYPE_CHECKING:  # only for the type of Mismatch.apply; never imported at run time
    from typing import TypeVar

    _Robot = TypeVar("_Robot", bound="ScalableRobot")

PAPER_CONDITIONS = Path(__file__).resolve().parent / "data" / "paper_conditions.yaml"
SHAPES = ("raised_sine", "sine", "constant")
INITIAL_STATES = ("home", "reference")
# The runtime precomputes the whole reference per period (hil_runtime.reference): one hour at 1 kHz
# is 3.6 M rows, ~0.5 GB and ~1.6 s to build. Longer runs are a loop of conditions, not one.
MAX_DURATION_S = 3600.0
MAX_FREQUENCY_HZ = 1000.0  # no arm tracks more; keeps omega * t far from float's precision limit
MAX_ABS_PHASE_S = 10 * MAX_DURATION_S
_TWO_PI = 2.0 * math.pi


class ConditionError(ValueError):
    """A conditions file or condition that cannot be used. Printed as one line by the CLI."""

    exit_code = 2


class JointLimits(Protocol):
    """What a reference is checked against: a robot model or the runtime's configured limits."""

    name: str

    @property
    def n_joints(self) -> int: ...

    @property
    def position_lower_rad(self) -> np.ndarray: ...

    @property
    def position_upper_rad(self) -> np.ndarray: ...

    @property
    def velocity_limit_rad_s(self) -> np.ndarray: ...


class ScalableRobot(Protocol):
    """The two operations a plant mismatch needs (``models.robots.RobotModel`` has them)."""

    def scaled(self, mass_scale: Any = 1.0, inertia_scale: Any = 1.0) -> Self: ...

    def with_payload(self, mass_kg: float, com_in_ee_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Self: ...


@dataclass(frozen=True)
class Disturbance:
    """A rectangular joint-torque pulse added to the plant: torque_nm over [time_s, time_s + duration_s]."""

    time_s: float = 2.0
    torque_nm: tuple[float, ...] = (1.0, 1.0, 5.0, 5.0, 10.0, 10.0)
    duration_s: float = 2.0e-5

    @property
    def impulse_nm_s(self) -> np.ndarray:
        return np.asarray(self.torque_nm) * self.duration_s


@dataclass(frozen=True)
class Mismatch:
    """How the simulated plant differs from the nominal model the controllers use."""

    payload_kg: float = 0.0  # point mass on the flange
    payload_com_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # in the flange frame
    mass_scale: tuple[float, ...] | float = 1.0  # per link
    inertia_scale: tuple[float, ...] | float = 1.0  # per link, rotational inertia about the COM
    viscous_friction_nm_s: tuple[float, ...] | float = 0.0  # per joint, tau_f = -b qd
    coulomb_friction_nm: tuple[float, ...] | float = 0.0  # per joint, tau_f = -fc tanh(qd / 0.01)

    def apply(self, robot: _Robot) -> _Robot:
        """The plant: ``robot`` (a ``models.robots.RobotModel``) scaled and carrying the payload."""
        plant = robot.scaled(np.asarray(self.mass_scale, float), np.asarray(self.inertia_scale, float))
        return plant.with_payload(self.payload_kg, self.payload_com_m) if self.payload_kg else plant

    @property
    def is_nominal(self) -> bool:
        return self == Mismatch()


@dataclass(frozen=True)
class Condition:
    """One operating condition: q_ref(t) = offset + A * shape(2 pi f (t - phase))."""

    name: str
    amplitude_rad: tuple[float, ...]
    frequency_hz: tuple[float, ...]
    duration_s: float = 5.0
    shape: str = "raised_sine"
    phase_s: float = 2.5
    offset_rad: tuple[float, ...] | None = None
    initial_state: str = "home"
    disturbance: Disturbance | None = field(default_factory=Disturbance)
    mismatch: Mismatch = field(default_factory=Mismatch)

    @property
    def n_joints(self) -> int:
        return len(self.amplitude_rad)

    def reference(self, t_s: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q_d, qd_d, qdd_d), each shaped t_s.shape + (N,)."""
        t = np.asarray(t_s, dtype=np.float64)[..., None]
        amp = np.asarray(self.amplitude_rad)
        offset = np.zeros_like(amp) if self.offset_rad is None else np.asarray(self.offset_rad)
        omega = 2.0 * math.pi * np.asarray(self.frequency_hz)
        phase = omega * (t - self.phase_s)
        if self.shape == "raised_sine":  # the paper's Eq. 27
            return (
                offset + 0.5 * amp * (1.0 + np.sin(phase)),
                0.5 * amp * omega * np.cos(phase),
                -0.5 * amp * omega**2 * np.sin(phase),
            )
        if self.shape == "sine":
            return offset + amp * np.sin(phase), amp * omega * np.cos(phase), -amp * omega**2 * np.sin(phase)
        zeros = np.zeros(t.shape[:-1] + amp.shape)
        return offset + amp + zeros, zeros, zeros.copy()

    def initial_position(self) -> np.ndarray:
        return self.reference(0.0)[0] if self.initial_state == "reference" else np.zeros(self.n_joints)

    def extrema(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(lowest q, highest q, highest |qd|) per joint over [0, duration_s], exact (from the
        shape, not from samples: a peak between samples or a frequency the samples alias counts)."""
        amp = np.asarray(self.amplitude_rad, float)
        offset = np.zeros_like(amp) if self.offset_rad is None else np.asarray(self.offset_rad, float)
        if self.shape == "constant":
            return offset + amp, offset + amp, np.zeros_like(amp)
        omega = _TWO_PI * np.asarray(self.frequency_hz, float)
        start, end = -omega * self.phase_s, omega * (self.duration_s - self.phase_s)  # the phase's span
        sin_low, sin_high = _sin_range(start, end)
        cos_low, cos_high = _sin_range(start + math.pi / 2, end + math.pi / 2)  # cos x = sin(x + pi/2)
        cos_abs = np.maximum(np.abs(cos_low), np.abs(cos_high))
        scale = 0.5 * amp if self.shape == "raised_sine" else amp
        base = offset + (0.5 * amp if self.shape == "raised_sine" else 0.0)
        ends = np.stack([base + scale * sin_low, base + scale * sin_high])
        return ends.min(axis=0), ends.max(axis=0), np.abs(scale * omega) * cos_abs

    def check_limits(self, limits: JointLimits, source: str = "condition") -> None:
        """Refuse a reference leaving the joint position or velocity limits (one-line error)."""
        if self.n_joints != limits.n_joints:
            raise ConditionError(
                f"{source}: {self.name}: amplitude_rad has {self.n_joints} joints, "
                f"robot {limits.name} has {limits.n_joints}"
            )
        lowest, highest, fastest = self.extrema()
        lower, upper = np.asarray(limits.position_lower_rad), np.asarray(limits.position_upper_rad)
        velocity = np.asarray(limits.velocity_limit_rad_s)
        checks = (
            (highest > upper + 1e-12, highest, upper, "position"),
            (lowest < lower - 1e-12, lowest, lower, "position"),
            (fastest > velocity + 1e-12, fastest, velocity, "velocity"),
        )
        for bad, worst, limit, what in checks:
            if bad.any():
                j = int(np.flatnonzero(bad)[0])
                raise ConditionError(
                    f"{source}: {self.name}: reference {what} reaches {worst[j]:.3f} on joint {j + 1}, "
                    f"beyond its limit {limit[j]:.3f}"
                )


def _sin_range(start: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) of sin over [start, end] per element: -1 / 1 where a trough / crest lies inside
    (rounded outward: a crest within 1e-9 rad of the span counts), else the ends' values."""

    def reaches(peak: float) -> np.ndarray:
        first = np.ceil((start - peak) / _TWO_PI - 1e-9)
        inside: np.ndarray = (end - start >= _TWO_PI) | (peak + first * _TWO_PI <= end + 1e-9)
        return inside

    ends_low, ends_high = np.minimum(np.sin(start), np.sin(end)), np.maximum(np.sin(start), np.sin(end))
    return np.where(reaches(-math.pi / 2), -1.0, ends_low), np.where(reaches(math.pi / 2), 1.0, ends_high)


# --- the file format -----------------------------------------------------------------------------

_OPS: dict[type[ast.operator], Callable[[float, float], float]] = {
    ast.Add: operator.add,
    ast.Sub: operator.sub,
    ast.Mult: operator.mul,
    ast.Div: operator.truediv,
}


def _number(value: Any, where: str) -> float:
    """A float from a YAML number or a small arithmetic expression of pi ("pi/4", "-2*pi/3")."""
    if isinstance(value, bool):
        raise ConditionError(f"{where}: not a number ({value!r})")
    if isinstance(value, (int, float)):
        result = float(value)
    elif isinstance(value, str) and len(value) <= 200:

        def walk(node: ast.AST) -> float:
            if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)):
                return float(node.value)
            if isinstance(node, ast.Name) and node.id == "pi":
                return math.pi
            if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
                return -walk(node.operand) if isinstance(node.op, ast.USub) else walk(node.operand)
            if isinstance(node, ast.BinOp) and type(node.op) in _OPS:
                return _OPS[type(node.op)](walk(node.left), walk(node.right))
            raise ValueError

        try:
            result = walk(ast.parse(value.strip(), mode="eval").body)
        except (ValueError, SyntaxError, ZeroDivisionError, OverflowError, RecursionError, MemoryError):
            raise ConditionError(f"{where}: not a number ({value!r})") from None
    else:
        raise ConditionError(f"{where}: not a number ({_short(value)})")
    if not math.isfinite(result):
        raise ConditionError(f"{where}: not finite ({value!r})")
    return result


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _vector(value: Any, where: str, n: int | None, allow_scalar: bool = False) -> tuple[float, ...]:
    if allow_scalar and not isinstance(value, (list, tuple)):
        if n is None:
            raise ConditionError(f"{where}: a scalar needs amplitude_rad to fix the joint count")
        return (_number(value, where),) * n
    if not isinstance(value, (list, tuple)):
        raise ConditionError(f"{where}: expected a list of numbers, got {_short(value)}")
    if n is not None and len(value) != n:
        raise ConditionError(f"{where}: expected {n} values, got {len(value)}")
    if not value:
        raise ConditionError(f"{where}: expected at least one value")
    return tuple(_number(v, f"{where}[{i}]") for i, v in enumerate(value))


def _at_least(values: tuple[float, ...] | float, bound: float, where: str, strict: bool) -> None:
    """Refuse any value below ``bound`` (or equal to it when ``strict``), naming the first one."""
    items = values if isinstance(values, tuple) else (values,)
    for i, v in enumerate(items):
        if v < bound or (strict and v == bound):
            index = f"[{i}]" if isinstance(values, tuple) and len(items) > 1 else ""
            relation = ">" if strict else ">="
            raise ConditionError(f"{where}{index}: must be {relation} {bound:g}, got {v:g}")


def _at_most(values: tuple[float, ...] | float, bound: float, where: str) -> None:
    """Refuse any value above ``bound``, naming the first one."""
    items = values if isinstance(values, tuple) else (values,)
    for i, v in enumerate(items):
        if v > bound:
            index = f"[{i}]" if isinstance(values, tuple) and len(items) > 1 else ""
            raise ConditionError(f"{where}{index}: must be <= {bound:g}, got {v:g}")


def _section(raw: dict[str, Any], key: str, where: str, fields: dict[str, str], n: int) -> dict[str, Any]:
    value = raw.get(key)
    if not isinstance(value, dict):
        raise ConditionError(f"{where}.{key}: expected a mapping, got {_short(value)}")
    unknown = set(value) - set(fields)
    if unknown:
        raise ConditionError(f"{where}.{key}: unknown field '{min(map(str, unknown))}' (known: {', '.join(fields)})")
    out: dict[str, Any] = {}
    for name, kind in fields.items():
        if name not in value:
            continue
        field_where = f"{where}.{key}.{name}"
        if kind == "scalar":
            out[name] = _number(value[name], field_where)
        elif kind == "vector3":
            out[name] = _vector(value[name], field_where, 3)
        else:
            out[name] = _vector(value[name], field_where, n, allow_scalar=True)
    return out


_CONDITION_FIELDS = {
    "name",
    "amplitude_rad",
    "frequency_hz",
    "duration_s",
    "shape",
    "phase_s",
    "offset_rad",
    "initial_state",
    "disturbance",
    "mismatch",
}
_DISTURBANCE_FIELDS = {"time_s": "scalar", "torque_nm": "vector", "duration_s": "scalar"}
_MISMATCH_FIELDS = {
    "payload_kg": "scalar",
    "payload_com_m": "vector3",
    "mass_scale": "vector",
    "inertia_scale": "vector",
    "viscous_friction_nm_s": "vector",
    "coulomb_friction_nm": "vector",
}


def _parse_condition(raw: Any, defaults: dict[str, Any], where: str) -> Condition:
    if not isinstance(raw, dict):
        raise ConditionError(f"{where}: expected a mapping, got {_short(raw)}")
    merged = {**defaults, **raw}
    unknown = set(merged) - _CONDITION_FIELDS
    if unknown:
        raise ConditionError(f"{where}: unknown field '{min(map(str, unknown))}'")
    if "amplitude_rad" not in merged:
        raise ConditionError(f"{where}.amplitude_rad: missing")
    amplitude = _vector(merged["amplitude_rad"], f"{where}.amplitude_rad", None)
    n = len(amplitude)
    shape = merged.get("shape", "raised_sine")
    if shape not in SHAPES:
        raise ConditionError(f"{where}.shape: unknown {_short(shape)} (known: {', '.join(SHAPES)})")
    initial = merged.get("initial_state", "home")
    if initial not in INITIAL_STATES:
        raise ConditionError(f"{where}.initial_state: unknown {_short(initial)} (known: {', '.join(INITIAL_STATES)})")
    duration = _number(merged.get("duration_s", 5.0), f"{where}.duration_s")
    if duration <= 0:
        raise ConditionError(f"{where}.duration_s: must be positive, got {duration:g}")
    if duration > MAX_DURATION_S:
        raise ConditionError(
            f"{where}.duration_s: {duration:g} s is above the limit {MAX_DURATION_S:g} s "
            "(the runtime precomputes the reference; run longer as several conditions)"
        )
    frequency = _vector(merged.get("frequency_hz", 0.1), f"{where}.frequency_hz", n, allow_scalar=True)
    _at_least(frequency, 0.0, f"{where}.frequency_hz", strict=False)
    _at_most(frequency, MAX_FREQUENCY_HZ, f"{where}.frequency_hz")
    disturbance: Disturbance | None = None
    if merged.get("disturbance") is not None:
        disturbance = Disturbance(**_section(merged, "disturbance", where, _DISTURBANCE_FIELDS, n))
        if len(disturbance.torque_nm) != n:  # the default torque has six joints
            raise ConditionError(
                f"{where}.disturbance.torque_nm: expected {n} values, got {len(disturbance.torque_nm)}"
            )
        _at_least(disturbance.time_s, 0.0, f"{where}.disturbance.time_s", strict=False)
        _at_least(disturbance.duration_s, 0.0, f"{where}.disturbance.duration_s", strict=False)
        _at_most(disturbance.duration_s, duration, f"{where}.disturbance.duration_s")
        if disturbance.time_s >= duration:
            raise ConditionError(
                f"{where}.disturbance.time_s: {disturbance.time_s:g} s is not before the end of the run "
                f"({duration:g} s)"
            )
    mismatch = Mismatch()
    if merged.get("mismatch") is not None:
        mismatch = Mismatch(**_section(merged, "mismatch", where, _MISMATCH_FIELDS, n))
        mw = f"{where}.mismatch"
        _at_least(mismatch.payload_kg, 0.0, f"{mw}.payload_kg", strict=False)
        _at_least(mismatch.mass_scale, 0.0, f"{mw}.mass_scale", strict=True)
        _at_least(mismatch.inertia_scale, 0.0, f"{mw}.inertia_scale", strict=True)
        _at_least(mismatch.viscous_friction_nm_s, 0.0, f"{mw}.viscous_friction_nm_s", strict=False)
        _at_least(mismatch.coulomb_friction_nm, 0.0, f"{mw}.coulomb_friction_nm", strict=False)
    offset = merged.get("offset_rad")
    name = merged.get("name", where)
    if not isinstance(name, (str, int)) or isinstance(name, bool):
        raise ConditionError(f"{where}.name: expected a string, got {_short(name)}")
    phase = _number(merged.get("phase_s", duration / 2.0), f"{where}.phase_s")
    if abs(phase) > MAX_ABS_PHASE_S:
        raise ConditionError(f"{where}.phase_s: |{phase:g}| s is above the limit {MAX_ABS_PHASE_S:g} s")
    return Condition(
        name=str(name),
        amplitude_rad=amplitude,
        frequency_hz=frequency,
        duration_s=duration,
        shape=shape,
        phase_s=phase,
        offset_rad=None if offset is None else _vector(offset, f"{where}.offset_rad", n),
        initial_state=initial,
        disturbance=disturbance,
        mismatch=mismatch,
    )


def _read_yaml(path: Path) -> Any:
    """The YAML document in ``path``; a one-line error for missing, binary or malformed files."""
    return read_yaml_config(path, ConditionError, "a conditions file")


def parse_conditions(raw: Any, source: str) -> list[Condition]:
    """Conditions from an already-parsed YAML document; ``source`` names it in errors."""
    if raw is None:
        raise ConditionError(f"{source}: empty file (expected a 'conditions' list)")
    if not isinstance(raw, dict) or not isinstance(raw.get("conditions"), list) or not raw["conditions"]:
        raise ConditionError(f"{source}: conditions: expected a non-empty list")
    unknown = set(raw) - {"defaults", "conditions"}
    if unknown:
        raise ConditionError(
            f"{source}: unknown top-level field '{min(map(str, unknown))}' (known: defaults, conditions)"
        )
    defaults = raw.get("defaults") or {}
    if not isinstance(defaults, dict):
        raise ConditionError(f"{source}: defaults: expected a mapping")
    conditions = [
        _parse_condition(item, defaults, f"{source}: conditions[{i}]") for i, item in enumerate(raw["conditions"])
    ]
    names = [c.name for c in conditions]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise ConditionError(f"{source}: conditions: duplicate name '{duplicates[0]}'")
    return conditions


def load_conditions(path: str | Path | None = None, limits: JointLimits | None = None) -> list[Condition]:
    """Conditions from a YAML file (the paper's five when ``path`` is None), checked against ``limits``."""
    path = Path(path) if path is not None else PAPER_CONDITIONS
    conditions = parse_conditions(_read_yaml(path), path.name)
    if limits is not None:
        for c in conditions:
            c.check_limits(limits, source=path.name)
    return conditions
