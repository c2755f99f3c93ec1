"""Realism profiles: one YAML format, validated once, bound to an arm (docs/realism.md).

A profile is a built-in name (``ideal``, ``realistic``, ``harsh``: the files next to this module in
``realism_profiles/``) or a path to a YAML file of the same schema. Bad values (negative or
non-finite, an unknown field, a per-joint list of the wrong length, a torque bandwidth above the
Nyquist rate of the plant's physics step, a velocity filter above the control period's) raise
:class:`~sim_target.realism.RealismError`: one line naming the file and the field, exit code 2.

A per-joint value is a scalar (every joint), an explicit list (exactly one value per joint of the
arm it is bound to), ``{repeat: [...]}`` (the pattern repeated over the joints), or, for the
torque-like fields, ``{scaled: [...]}``: a reference arm's values (the profile's
``reference_torque_limit_nm``) carried to any arm by the joint's torque limit
(:func:`scale_by_torque_limit`). The shipped profiles use the last two, so they apply to an arm of
any joint count; on their reference arm (ur5_paper) they give the listed values exactly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from drivers.config import format_validation_error, read_yaml_config
from sim_target.realism import Actuation, PlantErrors, RealismError, RealismSpec, Sensing

PROFILE_DIR = Path(__file__).with_name("realism_profiles")
PROFILE_NAMES = ("ideal", "realistic", "harsh")

_NonNegative = Annotated[float, Field(ge=0)]
_Positive = Annotated[float, Field(gt=0)]
_Counts = Annotated[int, Field(ge=0, le=2**32)]


class _Section(BaseModel):
    # allow_inf_nan=False: NaN or infinity is "not a finite number"; extra="forbid": a misspelt field
    # is an error, not a silently ideal default
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class Repeated(_Section):
    """``{repeat: [a, b]}``: a, b, a, b, ... over the arm's joints, whatever their count."""

    repeat: tuple[_NonNegative, ...] = Field(min_length=1)


class ScaledByTorqueLimit(_Section):
    """``{scaled: [...]}``: the reference arm's per-joint values (one per entry of the profile's
    ``reference_torque_limit_nm``), carried to each joint by its torque limit."""

    scaled: tuple[_NonNegative, ...] = Field(min_length=1)


#: a scalar for every joint, one value per joint, or a repeated pattern
PerJoint = _NonNegative | tuple[_NonNegative, ...] | Repeated
#: a torque-like per-joint value: also scaled from the reference arm by the joint's torque limit
TorquePerJoint = PerJoint | ScaledByTorqueLimit


class SensingSection(_Section):
    encoder_counts_per_rev: _Counts | tuple[_Counts, ...] = 0  # joint-side increments per revolution; 0: exact
    encoder_noise_rad: PerJoint = 0.0
    velocity: Literal["true", "difference"] = "true"
    velocity_filter_cutoff_hz: float = Field(0.0, ge=0)  # 0: no filter
    velocity_noise_rad_s: PerJoint = 0.0
    delay_periods: int = Field(0, ge=0, le=100)


class ActuationSection(_Section):
    torque_bandwidth_hz: float = Field(0.0, ge=0)  # 0: ideal torque source
    rated_torque_ratio_of_limit: PerJoint = 0.0  # 0x6076 / torque limit; quantum 1 per mille of it; 0: exact
    torque_ripple_ratio: PerJoint = 0.0
    torque_ripple_cycles_per_rev: PerJoint = 0.0
    torque_dead_band_nm: TorquePerJoint = 0.0


class PlantSection(_Section):
    viscous_friction_nm_s_per_rad: TorquePerJoint = 0.0
    coulomb_friction_nm: TorquePerJoint = 0.0
    stribeck_friction_nm: TorquePerJoint = 0.0
    stribeck_velocity_rad_s: PerJoint = 0.05
    friction_smoothing_velocity_rad_s: float = Field(0.01, gt=0)
    payload_kg: float = Field(0.0, ge=0, le=1000)
    payload_com_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    payload_inertia_kg_m2: tuple[_NonNegative, _NonNegative, _NonNegative] = (0.0, 0.0, 0.0)
    mass_scale: PerJoint = 1.0  # per link
    inertia_scale: PerJoint = 1.0  # per link


class RealismProfile(_Section):
    """The file format (every section optional; omitted values are the ideal world's)."""

    description: str = ""
    seed: int = Field(0, ge=0)
    # the torque limits of the arm whose values `{scaled: [...]}` lists give (ur5_paper's in the shipped ones)
    reference_torque_limit_nm: tuple[_Positive, ...] | None = None
    sensing: SensingSection = SensingSection()
    actuation: ActuationSection = ActuationSection()
    plant: PlantSection = PlantSection()


def profile_path(name_or_path: str | Path) -> Path:
    """The file of a built-in profile name, or the path itself."""
    text = str(name_or_path)
    if text in PROFILE_NAMES:
        return PROFILE_DIR / f"{text}.yaml"
    return Path(text)


def read_profile(name_or_path: str | Path) -> tuple[RealismProfile, str]:
    """The validated profile and its source (for error lines)."""
    path = profile_path(name_or_path)
    if not path.is_file():
        raise RealismError(f"--realism: '{name_or_path}' is neither a profile ({', '.join(PROFILE_NAMES)}) nor a file")
    data = read_yaml_config(path, RealismError, "a realism profile")
    return parse_profile(data, str(path)), str(path)


def parse_profile(data: Any, source: str) -> RealismProfile:
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise RealismError(f"{source}: expected a mapping of realism settings, got {type(data).__name__}")
    try:
        return RealismProfile.model_validate(data)
    except ValidationError as exc:
        raise RealismError(format_validation_error(source, exc)) from None


def scale_by_torque_limit(
    reference_values: np.ndarray, reference_limit_nm: np.ndarray, limit_nm: np.ndarray
) -> np.ndarray:
    """Each joint's value from the reference arm's, by its torque limit (docs/realism.md, "Any arm").

    The reference's value per N·m of torque limit is interpolated linearly in the torque limit between
    the reference's joints and held at the end values beyond them; joint j gets limit_j times it. A
    joint whose limit is one of the reference's gets that joint's value exactly (so the reference arm
    gets its own list bit for bit). Reference joints of one limit must carry one value (ValueError).
    """
    values = np.asarray(reference_values, dtype=float)
    ref_limit = np.asarray(reference_limit_nm, dtype=float)
    limit = np.asarray(limit_nm, dtype=float)
    classes = np.unique(ref_limit)  # sorted
    class_value = np.empty_like(classes)
    for k, level in enumerate(classes):
        members = values[ref_limit == level]
        if np.any(members != members[0]):
            raise ValueError(f"the reference joints of {level:g} N·m carry different values {members.tolist()}")
        class_value[k] = members[0]
    per_nm = np.interp(limit, classes, class_value / classes)
    scaled = per_nm * limit
    exact = np.searchsorted(classes, limit).clip(0, classes.size - 1)
    return np.where(classes[exact] == limit, class_value[exact], scaled)


def _per_joint(value: float | tuple[float, ...], n: int, source: str, field: str) -> np.ndarray:
    array = np.asarray(value, dtype=float)
    if array.ndim == 0:
        return np.full(n, float(array))
    if array.shape != (n,):
        raise RealismError(f"{source}: {field}: expected one value or {n} (one per joint), got {array.size}")
    return array


def bind_profile(
    profile: RealismProfile,
    source: str,
    n_joints: int,
    period_s: float,
    physics_step_s: float,
    torque_limit_nm: np.ndarray | list[float],
    seed: int | None = None,
) -> RealismSpec:
    """The profile for one arm and one plant: per-joint arrays, rates checked against the physics
    step (``period_s / substeps`` of the plant that applies it)."""
    s, a, p = profile.sensing, profile.actuation, profile.plant
    nyquist_hz = 0.5 / physics_step_s
    if a.torque_bandwidth_hz > nyquist_hz:
        raise RealismError(
            f"{source}: actuation.torque_bandwidth_hz: {a.torque_bandwidth_hz:g} Hz is above the Nyquist rate "
            f"of the plant's physics step ({physics_step_s:g} s: {nyquist_hz:g} Hz)"
        )
    if s.velocity_filter_cutoff_hz > 0.5 / period_s:
        raise RealismError(
            f"{source}: sensing.velocity_filter_cutoff_hz: {s.velocity_filter_cutoff_hz:g} Hz is above the Nyquist "
            f"rate of the control period ({0.5 / period_s:g} Hz)"
        )
    limit = np.broadcast_to(np.asarray(torque_limit_nm, dtype=float), (n_joints,))

    def joint(value: Any, field: str) -> np.ndarray:
        if isinstance(value, Repeated):
            return np.resize(np.asarray(value.repeat, dtype=float), n_joints)
        if isinstance(value, ScaledByTorqueLimit):
            return _scaled(value, field)
        return _per_joint(value, n_joints, source, field)

    def _scaled(value: ScaledByTorqueLimit, field: str) -> np.ndarray:
        reference = profile.reference_torque_limit_nm
        if reference is None:
            raise RealismError(f"{source}: {field}: 'scaled' needs the profile's reference_torque_limit_nm")
        if len(value.scaled) != len(reference):
            raise RealismError(
                f"{source}: {field}: scaled: expected {len(reference)} values (one per joint of "
                f"reference_torque_limit_nm), got {len(value.scaled)}"
            )
        try:
            return scale_by_torque_limit(np.asarray(value.scaled), np.asarray(reference), limit)
        except ValueError as exc:
            raise RealismError(f"{source}: {field}: {exc}") from None

    sensing = Sensing(
        encoder_counts_per_rev=joint(s.encoder_counts_per_rev, "sensing.encoder_counts_per_rev"),
        encoder_noise_rad=joint(s.encoder_noise_rad, "sensing.encoder_noise_rad"),
        velocity_from_difference=s.velocity == "difference",
        velocity_filter_cutoff_hz=s.velocity_filter_cutoff_hz,
        velocity_noise_rad_s=joint(s.velocity_noise_rad_s, "sensing.velocity_noise_rad_s"),
        delay_periods=s.delay_periods,
    )
    actuation = Actuation(
        torque_bandwidth_hz=a.torque_bandwidth_hz,
        torque_quantum_nm=joint(a.rated_torque_ratio_of_limit, "actuation.rated_torque_ratio_of_limit")
        * limit
        / 1000.0,
        torque_ripple_ratio=joint(a.torque_ripple_ratio, "actuation.torque_ripple_ratio"),
        torque_ripple_cycles_per_rev=joint(a.torque_ripple_cycles_per_rev, "actuation.torque_ripple_cycles_per_rev"),
        torque_dead_band_nm=joint(a.torque_dead_band_nm, "actuation.torque_dead_band_nm"),
    )
    plant = PlantErrors(
        viscous_friction_nm_s_per_rad=joint(p.viscous_friction_nm_s_per_rad, "plant.viscous_friction_nm_s_per_rad"),
        coulomb_friction_nm=joint(p.coulomb_friction_nm, "plant.coulomb_friction_nm"),
        stribeck_friction_nm=joint(p.stribeck_friction_nm, "plant.stribeck_friction_nm"),
        stribeck_velocity_rad_s=joint(p.stribeck_velocity_rad_s, "plant.stribeck_velocity_rad_s"),
        friction_smoothing_velocity_rad_s=p.friction_smoothing_velocity_rad_s,
        payload_kg=p.payload_kg,
        payload_com_m=p.payload_com_m,
        payload_inertia_kg_m2=p.payload_inertia_kg_m2,
        mass_scale=joint(p.mass_scale, "plant.mass_scale"),
        inertia_scale=joint(p.inertia_scale, "plant.inertia_scale"),
    )
    name = source if Path(source).parent != PROFILE_DIR else Path(source).stem
    return RealismSpec(name, period_s, sensing, actuation, plant, profile.seed if seed is None else seed)


def load_realism(
    name_or_path: str | Path,
    n_joints: int,
    period_s: float,
    physics_step_s: float,
    torque_limit_nm: np.ndarray | list[float],
    seed: int | None = None,
) -> RealismSpec:
    """Read, validate and bind a profile in one call (one line and exit 2 on any bad value)."""
    profile, source = read_profile(name_or_path)
    return bind_profile(profile, source, n_joints, period_s, physics_step_s, torque_limit_nm, seed)


def ideal_spec(n_joints: int, period_s: float) -> RealismSpec:
    """Today's world, without reading a file."""
    return bind_profile(RealismProfile(), "ideal", n_joints, period_s, period_s, np.ones(n_joints))


__all__ = [
    "PROFILE_NAMES",
    "RealismProfile",
    "Repeated",
    "ScaledByTorqueLimit",
    "bind_profile",
    "ideal_spec",
    "load_realism",
    "parse_profile",
    "profile_path",
    "read_profile",
    "scale_by_torque_limit",
]
