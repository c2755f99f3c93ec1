"""The robot's URDF for recordings and live views, found without importing ``models``.

A bundle's manifest names its robot's URDF (``robot.urdf_file``) and pins its sha256; the file
ships in ``models/robots/data``. :func:`find_urdf` looks there (by the package's location, not by
importing it: the runtime never imports ``models``) and beside the bundle, and accepts a file only
when its sha256 is the manifest's: a recording never carries another arm's description.
"""

from __future__ import annotations

import hashlib
import importlib.util
import math
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path


class UrdfError(ValueError):
    """An explicit URDF that cannot be read or is not the bundle's; one line, exit code 2."""

    exit_code = 2


def _shipped_dirs() -> Iterator[Path]:
    spec = importlib.util.find_spec("models")  # locates the package without running it
    for location in (spec.submodule_search_locations or []) if spec is not None else []:
        yield Path(location) / "robots" / "data"


def find_urdf(
    urdf_file: str,
    sha256: str | None = None,
    bundle_dir: Path | None = None,
    explicit: Path | None = None,
) -> Path | None:
    """The URDF named ``urdf_file`` (a bare file name, e.g. ``ur5_paper.urdf``) whose sha256 is
    ``sha256`` (unchecked when None); ``explicit`` first (UrdfError if it does not match), then
    beside the bundle and in the shipped robot data. None when no file matches."""
    if explicit is not None:
        try:
            data = explicit.read_bytes()
        except OSError as exc:
            raise UrdfError(f"--urdf {explicit}: {exc.strerror or exc}") from None
        if sha256 is not None and hashlib.sha256(data).hexdigest() != sha256:
            raise UrdfError(f"--urdf {explicit}: sha256 differs from the bundle's robot.urdf_sha256 ({sha256[:12]}…)")
        return explicit
    name = Path(urdf_file).name
    candidates = [bundle_dir / name, bundle_dir.parent / name] if bundle_dir is not None else []
    candidates += [directory / name for directory in _shipped_dirs()]
    for candidate in candidates:
        if candidate.is_file() and (sha256 is None or hashlib.sha256(candidate.read_bytes()).hexdigest() == sha256):
            return candidate
    return None


# --- forward kinematics for live views (Foxglove's 3D panel draws links from /tf) ---------------


@dataclass(frozen=True)
class JointFrame:
    """One URDF joint: the transform from ``parent`` to ``child`` link at position ``q``."""

    name: str
    kind: str  # revolute, continuous, prismatic, fixed
    parent: str
    child: str
    xyz: tuple[float, float, float]
    quaternion_xyzw: tuple[float, float, float, float]  # of the origin's rpy
    axis: tuple[float, float, float]

    def transform(self, q: float) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
        """(translation [m], rotation quaternion x, y, z, w) of the child in the parent at ``q``."""
        if self.kind in ("revolute", "continuous"):
            return self.xyz, _multiply(self.quaternion_xyzw, _axis_angle(self.axis, q))
        if self.kind == "prismatic":
            offset = _rotate(self.quaternion_xyzw, tuple(a * q for a in self.axis))  # type: ignore[arg-type]  # 3 floats
            return (self.xyz[0] + offset[0], self.xyz[1] + offset[1], self.xyz[2] + offset[2]), self.quaternion_xyzw
        return self.xyz, self.quaternion_xyzw


def _floats(text: str | None, default: str) -> tuple[float, float, float]:
    a, b, c = (float(v) for v in (text or default).split())
    return a, b, c


def _rpy_quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def _axis_angle(axis: tuple[float, float, float], angle: float) -> tuple[float, float, float, float]:
    norm = math.sqrt(sum(a * a for a in axis)) or 1.0
    s = math.sin(angle / 2) / norm
    return axis[0] * s, axis[1] * s, axis[2] * s, math.cos(angle / 2)


def _multiply(
    a: tuple[float, float, float, float], b: tuple[float, float, float, float]
) -> tuple[float, float, float, float]:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def _rotate(q: tuple[float, float, float, float], v: tuple[float, float, float]) -> tuple[float, float, float]:
    x, y, z, _ = _multiply(_multiply(q, (v[0], v[1], v[2], 0.0)), (-q[0], -q[1], -q[2], q[3]))
    return x, y, z


def joint_frames(urdf_text: str, source: str = "URDF") -> list[JointFrame]:
    """Every joint of a URDF, in file order; UrdfError (one line) when it cannot be read."""
    try:
        root = ET.fromstring(urdf_text)
    except ET.ParseError as exc:
        raise UrdfError(f"{source}: not XML ({exc})") from None
    frames = []
    for joint in root.iter("joint"):
        parent, child = joint.find("parent"), joint.find("child")
        if parent is None or child is None:
            raise UrdfError(f"{source}: joint {joint.get('name')!r} without parent or child")
        origin, axis = joint.find("origin"), joint.find("axis")
        try:
            xyz = _floats(origin.get("xyz") if origin is not None else None, "0 0 0")
            rpy = _floats(origin.get("rpy") if origin is not None else None, "0 0 0")
            axis_xyz = _floats(axis.get("xyz") if axis is not None else None, "1 0 0")
        except ValueError:
            raise UrdfError(f"{source}: joint {joint.get('name')!r}: bad origin or axis numbers") from None
        frames.append(
            JointFrame(
                str(joint.get("name")),
                str(joint.get("type", "fixed")),
                str(parent.get("link")),
                str(child.get("link")),
                xyz,
                _rpy_quaternion(*rpy),
                axis_xyz,
            )
        )
    return frames
