"""Operating conditions as data: reference trajectories, disturbance and plant-model mismatch.

The paper's five conditions are in ``models/data/paper_conditions.yaml``; users write their own in
the same format (docs/conditions.md). ``random_conditions`` draws seeded ones inside the limits.

    conditions = load_conditions()                 # the paper's five
    conditions = load_conditions("my_conditions.yaml")
    q_d, qd_d, qdd_d = conditions[0].reference(t_s)  # t_s scalar or (T,) -> (..., N)
"""

from __future__ import annotations

import ast
import math
import operator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from models.errors import ModelInputError
from models.robots import RobotModel

PAPER_CONDITIONS = Path(__file__).resolve().parent / "data" / "paper_conditions.yaml"
SHAPES = ("raised_sine", "sine", "constant")
INITIAL_STATES = ("home", "reference")


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

    def apply(self, robot: RobotModel) -> RobotModel:
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
            return (offset + 0.5 * amp * (1.0 + np.sin(phase)), 0.5 * amp * omega * np.cos(phase),
                    -0.5 * amp * omega**2 * np.sin(phase))  # fmt: skip
        if self.shape == "sine":
            return offset + amp * np.sin(phase), amp * omega * np.cos(phase), -amp * omega**2 * np.sin(phase)
        zeros = np.zeros(t.shape[:-1] + amp.shape)
        return offset + amp + zeros, zeros, zeros.copy()

    def initial_position(self) -> np.ndarray:
        return self.reference(0.0)[0] if self.initial_state == "reference" else np.zeros(self.n_joints)

    def check_limits(self, robot: RobotModel, source: str = "condition") -> None:
        """Refuse a reference leaving the joint position or velocity limits (one-line error)."""
        if self.n_joints != robot.n_joints:
            raise ModelInputError(
                f"{source}: {self.name}: amplitude_rad has {self.n_joints} joints, robot {robot.name} has {robot.n_joints}"
            )
        t = np.linspace(0.0, self.duration_s, 2001)
        q, qd, _ = self.reference(t)
        lower, upper = robot.position_lower_rad, robot.position_upper_rad
        checks = (
            (q, np.max(q, axis=0) > upper + 1e-12, np.max(q, axis=0), upper, "position"),
            (q, np.min(q, axis=0) < lower - 1e-12, np.min(q, axis=0), lower, "position"),
            (qd, np.max(np.abs(qd), axis=0) > robot.velocity_limit_rad_s + 1e-12, np.max(np.abs(qd), axis=0),
             robot.velocity_limit_rad_s, "velocity"),
        )  # fmt: skip
        for _, bad, worst, limit, what in checks:
            if bad.any():
                j = int(np.flatnonzero(bad)[0])
                raise ModelInputError(
                    f"{source}: {self.name}: reference {what} reaches {worst[j]:.3f} on joint {j + 1}, "
                    f"beyond its limit {limit[j]:.3f}"
                )


# --- the file format -----------------------------------------------------------------------------

_OPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv}


def _number(value: Any, where: str) -> float:
    """A float from a YAML number or a small arithmetic expression of pi ("pi/4", "-2*pi/3")."""
    if isinstance(value, bool):
        raise ModelInputError(f"{where}: not a number ({value!r})")
    if isinstance(value, (int, float)):
        result = float(value)
    elif isinstance(value, str):

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
        except (ValueError, SyntaxError, ZeroDivisionError):
            raise ModelInputError(f"{where}: not a number ({value!r})") from None
    else:
        raise ModelInputError(f"{where}: not a number ({value!r})")
    if not math.isfinite(result):
        raise ModelInputError(f"{where}: not finite ({value!r})")
    return result


def _vector(value: Any, where: str, n: int | None, allow_scalar: bool = False) -> tuple[float, ...]:
    if allow_scalar and not isinstance(value, (list, tuple)):
        if n is None:
            raise ModelInputError(f"{where}: a scalar needs amplitude_rad to fix the joint count")
        return (_number(value, where),) * n
    if not isinstance(value, (list, tuple)):
        raise ModelInputError(f"{where}: expected a list of numbers, got {value!r}")
    if n is not None and len(value) != n:
        raise ModelInputError(f"{where}: expected {n} values, got {len(value)}")
    return tuple(_number(v, f"{where}[{i}]") for i, v in enumerate(value))


def _section(raw: dict, key: str, where: str, fields: dict[str, str], n: int) -> dict[str, Any]:
    value = raw.get(key)
    if not isinstance(value, dict):
        raise ModelInputError(f"{where}.{key}: expected a mapping, got {value!r}")
    unknown = set(value) - set(fields)
    if unknown:
        raise ModelInputError(f"{where}.{key}: unknown field '{sorted(unknown)[0]}' (known: {', '.join(fields)})")
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
            vec = _vector(value[name], field_where, n, allow_scalar=True)
            out[name] = vec
    return out


_CONDITION_FIELDS = {
    "name", "amplitude_rad", "frequency_hz", "duration_s", "shape", "phase_s", "offset_rad",
    "initial_state", "disturbance", "mismatch",
}  # fmt: skip


def _parse_condition(raw: Any, defaults: dict, where: str) -> Condition:
    if not isinstance(raw, dict):
        raise ModelInputError(f"{where}: expected a mapping, got {raw!r}")
    merged = {**defaults, **raw}
    unknown = set(merged) - _CONDITION_FIELDS
    if unknown:
        raise ModelInputError(f"{where}: unknown field '{sorted(unknown)[0]}'")
    if "amplitude_rad" not in merged:
        raise ModelInputError(f"{where}.amplitude_rad: missing")
    amplitude = _vector(merged["amplitude_rad"], f"{where}.amplitude_rad", None)
    n = len(amplitude)
    shape = merged.get("shape", "raised_sine")
    if shape not in SHAPES:
        raise ModelInputError(f"{where}.shape: unknown '{shape}' (known: {', '.join(SHAPES)})")
    initial = merged.get("initial_state", "home")
    if initial not in INITIAL_STATES:
        raise ModelInputError(f"{where}.initial_state: unknown '{initial}' (known: {', '.join(INITIAL_STATES)})")
    duration = _number(merged.get("duration_s", 5.0), f"{where}.duration_s")
    if duration <= 0:
        raise ModelInputError(f"{where}.duration_s: must be positive, got {duration}")
    disturbance: Disturbance | None = None
    if merged.get("disturbance") is not None:
        fields = {"time_s": "scalar", "torque_nm": "vector", "duration_s": "scalar"}
        disturbance = Disturbance(**_section(merged, "disturbance", where, fields, n))
        if disturbance.duration_s < 0 or disturbance.time_s < 0:
            raise ModelInputError(f"{where}.disturbance: time_s and duration_s must be >= 0")
    mismatch = Mismatch()
    if merged.get("mismatch") is not None:
        fields = {
            "payload_kg": "scalar", "payload_com_m": "vector3", "mass_scale": "vector", "inertia_scale": "vector",
            "viscous_friction_nm_s": "vector", "coulomb_friction_nm": "vector",
        }  # fmt: skip
        mismatch = Mismatch(**_section(merged, "mismatch", where, fields, n))
    offset = merged.get("offset_rad")
    return Condition(
        name=str(merged.get("name", where)),
        amplitude_rad=amplitude,
        frequency_hz=_vector(merged.get("frequency_hz", 0.1), f"{where}.frequency_hz", n, allow_scalar=True),
        duration_s=duration,
        shape=shape,
        phase_s=_number(merged.get("phase_s", duration / 2.0), f"{where}.phase_s"),
        offset_rad=None if offset is None else _vector(offset, f"{where}.offset_rad", n),
        initial_state=initial,
        disturbance=disturbance,
        mismatch=mismatch,
    )


def load_conditions(path: str | Path | None = None, robot: RobotModel | None = None) -> list[Condition]:
    """Conditions from a YAML file (the paper's five when ``path`` is None), checked against ``robot``."""
    path = Path(path) if path is not None else PAPER_CONDITIONS
    if not path.is_file():
        raise ModelInputError(f"{path}: file not found")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" at line {mark.line + 1}" if mark is not None else ""
        raise ModelInputError(f"{path.name}: not valid YAML{line}") from None
    if not isinstance(raw, dict) or not isinstance(raw.get("conditions"), list) or not raw["conditions"]:
        raise ModelInputError(f"{path.name}: conditions: expected a non-empty list")
    defaults = raw.get("defaults") or {}
    if not isinstance(defaults, dict):
        raise ModelInputError(f"{path.name}: defaults: expected a mapping")
    conditions = [
        _parse_condition(item, defaults, f"{path.name}: conditions[{i}]") for i, item in enumerate(raw["conditions"])
    ]
    names = [c.name for c in conditions]
    if len(set(names)) != len(names):
        raise ModelInputError(f"{path.name}: conditions: duplicate names")
    if robot is not None:
        for c in conditions:
            c.check_limits(robot, source=path.name)
    return conditions


def random_conditions(
    robot: RobotModel,
    count: int,
    seed: int,
    frequency_range_hz: tuple[float, float] = (0.05, 0.2),
    limit_fraction: float = 0.8,
    template: Condition | None = None,
) -> list[Condition]:
    """Seeded raised-sine conditions whose references stay inside ``limit_fraction`` of the limits."""
    rng = np.random.default_rng(seed)
    template = template or Condition(name="template", amplitude_rad=(0.0,) * robot.n_joints,
                                     frequency_hz=(0.1,) * robot.n_joints)  # fmt: skip
    pos_limit = np.minimum(robot.position_limit_rad, math.pi) * limit_fraction
    vel_limit = np.minimum(robot.velocity_limit_rad_s, 10.0) * limit_fraction
    out = []
    for k in range(count):
        freq = rng.uniform(*frequency_range_hz, size=robot.n_joints)
        # |A| bounded by the position range (the reference spans [0, A]) and by the peak velocity pi f |A|.
        max_amp = np.minimum(pos_limit, vel_limit / (math.pi * freq))
        amp = rng.uniform(-1.0, 1.0, size=robot.n_joints) * max_amp
        out.append(replace(template, name=f"R{seed}-{k:03d}", amplitude_rad=tuple(amp), frequency_hz=tuple(freq),
                           phase_s=float(rng.uniform(0.0, template.duration_s))))  # fmt: skip
    return out
