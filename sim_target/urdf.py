"""What the target needs to know from a URDF before pybullet loads it: joints, limits, inertials.

pybullet accepts a negative mass or inertia, and a revolute joint without ``<limit>``, and then
simulates nonsense (or crashes later); this reader refuses them first with one line naming the file
and the element. Light: the standard library and numpy, no pybullet.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

INERTIA_TOLERANCE = 1e-12  # kg m^2: rounding in a file's printed inertia is not a negative inertia


class UrdfError(ValueError):
    """A URDF the target refuses; one line naming the file and the element."""

    exit_code = 2


@dataclass(frozen=True)
class UrdfJoint:
    name: str
    type: str  # revolute, continuous, prismatic, fixed, ...
    lower_rad: float
    upper_rad: float
    effort_nm: float = math.inf  # <limit effort>; inf when the URDF gives none
    velocity_rad_s: float = math.inf  # <limit velocity>


def _number(path: Path, element: ET.Element, attribute: str, where: str, default: str | None = None) -> float:
    text = element.get(attribute, default)
    if text is None:
        raise UrdfError(f"{path}: {where} {attribute}: missing")
    try:
        value = float(text)
    except ValueError:
        raise UrdfError(f"{path}: {where} {attribute}: not a number ({text!r})") from None
    if not math.isfinite(value):
        raise UrdfError(f"{path}: {where} {attribute}: not finite ({text!r})")
    return value


def _check_inertial(path: Path, link: ET.Element) -> None:
    inertial = link.find("inertial")
    if inertial is None:
        return
    where = f"link '{link.get('name')}'"
    mass = inertial.find("mass")
    if mass is not None and _number(path, mass, "value", f"{where} <mass>") < 0:
        raise UrdfError(f"{path}: {where} <mass> value: negative ({mass.get('value')})")
    inertia = inertial.find("inertia")
    if inertia is None:
        return
    i = {k: _number(path, inertia, k, f"{where} <inertia>", "0") for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
    for k in ("ixx", "iyy", "izz"):
        if i[k] < -INERTIA_TOLERANCE:
            raise UrdfError(f"{path}: {where} <inertia> {k}: negative ({i[k]:g})")
    tensor = np.array([[i["ixx"], i["ixy"], i["ixz"]], [i["ixy"], i["iyy"], i["iyz"]], [i["ixz"], i["iyz"], i["izz"]]])
    smallest = float(np.linalg.eigvalsh(tensor)[0])
    if smallest < -INERTIA_TOLERANCE * max(1.0, float(np.abs(tensor).max())):
        raise UrdfError(f"{path}: {where} <inertia>: not positive semi-definite (principal moment {smallest:g})")


def read_urdf_joints(path: Path) -> list[UrdfJoint]:
    """The URDF's joints in file order, every inertial checked; UrdfError on anything pybullet
    would accept and then simulate wrongly."""
    if not path.is_file():
        raise UrdfError(f"{path}: URDF not found")
    try:
        data = path.read_bytes()
        root = ET.fromstring(data)
    except OSError as exc:
        raise UrdfError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except ET.ParseError as exc:
        raise UrdfError(f"{path}: not valid XML ({exc})") from None
    if root.tag != "robot":
        raise UrdfError(f"{path}: root element is <{root.tag}>, expected <robot>")
    for link in root.iter("link"):
        _check_inertial(path, link)
    joints = []
    for joint in root.findall("joint"):
        name, kind = joint.get("name", "?"), joint.get("type", "?")
        lower, upper = -math.inf, math.inf
        effort, velocity = math.inf, math.inf
        if kind in ("revolute", "prismatic"):
            limit = joint.find("limit")
            if limit is None:
                raise UrdfError(f"{path}: joint '{name}' <limit>: missing (a {kind} joint needs lower and upper)")
            where = f"joint '{name}' <limit>"
            lower = _number(path, limit, "lower", where, "0")
            upper = _number(path, limit, "upper", where, "0")
            if lower > upper:
                raise UrdfError(f"{path}: {where}: lower {lower:g} above upper {upper:g}")
            effort = _number(path, limit, "effort", where)
            velocity = _number(path, limit, "velocity", where)
            for attribute, value in (("effort", effort), ("velocity", velocity)):
                if value < 0:
                    raise UrdfError(f"{path}: {where} {attribute}: negative")
        joints.append(UrdfJoint(name, kind, lower, upper, effort or math.inf, velocity or math.inf))
    return joints
