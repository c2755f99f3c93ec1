"""Parse a URDF into the serial revolute chain the dynamics code works on.

The chain is the path from the root link to the deepest revolute joint. Every other link (fixed
children such as a flange or hand, and any joint off the chain, e.g. the Panda's prismatic fingers,
locked at zero) is merged rigidly into the body of its nearest chain ancestor, exactly as pinocchio
does for fixed joints, so the three consumers of one URDF agree.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import yaml

from hil_runtime.rate_limit import TorqueRate, torque_rate_limit_nm_s
from models.errors import ModelInputError

DATA_DIR = Path(__file__).resolve().parent / "data"
_MOVING = {"revolute", "continuous"}
_FLOATING = {"floating", "planar"}


def _example_robot_data_dir() -> Path:
    import sys

    for entry in sys.path:
        candidate = Path(entry) / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
        if candidate.is_dir():
            return candidate
    raise ModelInputError("robot data: example-robot-data is not installed (pip install example-robot-data)")


# name -> (URDF location, end-effector link, torque-rate rule), from data/robots.yaml: the one table,
# which the simulated target reads too without importing this package (sim_target/robots.py).
_BUILTIN: dict[str, tuple[str, str, TorqueRate | None]] = {
    str(name): (str(entry["urdf"]), str(entry["end_effector"]), entry.get("torque_rate"))
    for name, entry in yaml.safe_load((DATA_DIR / "robots.yaml").read_text()).items()
}


def robot_names() -> list[str]:
    return sorted(_BUILTIN)


def urdf_path(name: str) -> Path:
    """Path of a built-in robot's URDF (``ur5_paper``, ``ur5``, ``panda``)."""
    if name not in _BUILTIN:
        raise ModelInputError(f"robot: unknown name '{name}' (known: {', '.join(robot_names())}, or a .urdf path)")
    where = _BUILTIN[name][0]
    kind, rel = where.split(":", 1)
    return DATA_DIR / rel if kind == "local" else _example_robot_data_dir() / rel


@dataclass(frozen=True, eq=False)
class RobotModel:
    """A fixed-base serial chain of N revolute joints.

    Frame i is attached to link i at joint i. Joint i's frame at q_i = 0 is
    (``joint_rotation[i]``, ``joint_translation[i]``) relative to frame i-1 (frame -1 = base).
    Inertial data are per merged body, in its own frame, the inertia about the centre of mass.
    """

    name: str
    urdf_path: Path
    joint_names: tuple[str, ...]
    joint_rotation: np.ndarray  # (N, 3, 3)
    joint_translation: np.ndarray  # (N, 3) m
    joint_axis: np.ndarray  # (N, 3) unit, in joint frame
    mass_kg: np.ndarray  # (N,)
    com_m: np.ndarray  # (N, 3) in body frame
    inertia_kg_m2: np.ndarray  # (N, 3, 3) about the COM, body axes
    ee_rotation: np.ndarray  # (3, 3) end-effector frame in the last body's frame
    ee_translation: np.ndarray  # (3,)
    position_limit_rad: np.ndarray  # (N,) symmetric bound |q| <= this: min(|lower|, |upper|), conservative
    velocity_limit_rad_s: np.ndarray  # (N,)
    torque_limit_nm: np.ndarray  # (N,)
    gravity_m_s2: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    position_range_rad: np.ndarray | None = None  # (N, 2) [lower, upper] when not symmetric (e.g. Panda)
    # (N,) N·m/s: the commanded torque's rate bound (robots.yaml torque_rate; hil_runtime.rate_limit)
    torque_rate_limit_nm_s: np.ndarray | None = None

    @property
    def torque_rate_nm_s(self) -> np.ndarray:
        """Each joint's torque-rate bound (N·m/s): the registry's rule, else the documented default."""
        if self.torque_rate_limit_nm_s is not None:
            return self.torque_rate_limit_nm_s
        return torque_rate_limit_nm_s(None, self.torque_limit_nm)

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def position_lower_rad(self) -> np.ndarray:
        return -self.position_limit_rad if self.position_range_rad is None else self.position_range_rad[:, 0]

    @property
    def position_upper_rad(self) -> np.ndarray:
        return self.position_limit_rad if self.position_range_rad is None else self.position_range_rad[:, 1]

    def position_limit_ratio(self, q: np.ndarray) -> np.ndarray:
        """|q - mid| / half-range per joint: 1.0 on a limit, > 1 beyond it (|q| / limit when symmetric)."""
        lower, upper = self.position_lower_rad, self.position_upper_rad
        return np.abs(q - 0.5 * (lower + upper)) / (0.5 * (upper - lower))

    def with_payload(self, mass_kg: float, com_in_ee_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> RobotModel:
        """The same robot carrying a point mass rigidly fixed to the end-effector frame."""
        point = self.ee_rotation @ np.asarray(com_in_ee_m, float) + self.ee_translation
        mass, com, inertia = _combine(
            [(self.mass_kg[-1], self.com_m[-1], self.inertia_kg_m2[-1]), (float(mass_kg), point, np.zeros((3, 3)))]
        )
        return replace(
            self,
            name=f"{self.name}+payload{mass_kg:g}kg",
            mass_kg=_with_last(self.mass_kg, mass),
            com_m=_with_last(self.com_m, com),
            inertia_kg_m2=_with_last(self.inertia_kg_m2, inertia),
        )

    def scaled(self, mass_scale: np.ndarray | float = 1.0, inertia_scale: np.ndarray | float = 1.0) -> RobotModel:
        """Masses and rotational inertias scaled per link (plant-model mismatch)."""
        mass_scale = np.broadcast_to(np.asarray(mass_scale, float), (self.n_joints,))
        inertia_scale = np.broadcast_to(np.asarray(inertia_scale, float), (self.n_joints,))
        return replace(
            self,
            name=f"{self.name}*scaled",
            mass_kg=self.mass_kg * mass_scale,
            inertia_kg_m2=self.inertia_kg_m2 * inertia_scale[:, None, None],
        )


def _with_last(array: np.ndarray, value: np.ndarray | float) -> np.ndarray:
    out = np.array(array, copy=True)
    out[-1] = value
    return out


def rpy_to_matrix(rpy: np.ndarray) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _combine(parts: list[tuple[float, np.ndarray, np.ndarray]]) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass, COM and inertia about the COM of rigidly joined parts (parallel-axis theorem)."""
    mass = float(sum(m for m, _, _ in parts))
    if mass <= 0.0:
        return 0.0, np.zeros(3), np.zeros((3, 3))
    com = np.zeros(3)
    for m, c, _ in parts:
        com += m * np.asarray(c)
    com /= mass
    inertia = np.zeros((3, 3))
    for m, c, i_c in parts:
        d = np.asarray(c) - com
        inertia += i_c + m * (d @ d * np.eye(3) - np.outer(d, d))
    return mass, com, inertia


def _floats(path: Path, element: ET.Element, attribute: str, default: str | None, count: int) -> np.ndarray:
    text = element.get(attribute, default)
    where = f"{path.name}: <{element.tag}> {attribute}"
    if text is None:
        raise ModelInputError(f"{where}: missing")
    try:
        values = np.array([float(v) for v in text.split()])
    except ValueError:
        raise ModelInputError(f"{where}: not numeric ('{text}')") from None
    if values.size != count or not np.all(np.isfinite(values)):
        raise ModelInputError(f"{where}: expected {count} finite numbers, got '{text}'")
    return values


def _origin(path: Path, parent: ET.Element) -> tuple[np.ndarray, np.ndarray]:
    origin = parent.find("origin")
    if origin is None:
        return np.eye(3), np.zeros(3)
    return rpy_to_matrix(_floats(path, origin, "rpy", "0 0 0", 3)), _floats(path, origin, "xyz", "0 0 0", 3)


def _link_inertial(path: Path, link: ET.Element) -> tuple[float, np.ndarray, np.ndarray]:
    inertial = link.find("inertial")
    if inertial is None:
        return 0.0, np.zeros(3), np.zeros((3, 3))
    rotation, com = _origin(path, inertial)
    mass_el, inertia_el = inertial.find("mass"), inertial.find("inertia")
    if mass_el is None:
        raise ModelInputError(f"{path.name}: link '{link.get('name')}' <inertial> has no <mass>")
    mass = float(_floats(path, mass_el, "value", None, 1)[0])
    if mass < 0:
        raise ModelInputError(f"{path.name}: link '{link.get('name')}' <mass> value: negative")
    i = {k: 0.0 for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
    if inertia_el is not None:
        i = {k: float(_floats(path, inertia_el, k, "0", 1)[0]) for k in i}
    tensor = np.array([[i["ixx"], i["ixy"], i["ixz"]], [i["ixy"], i["iyy"], i["iyz"]], [i["ixz"], i["iyz"], i["izz"]]])
    # A physical inertia is positive semi-definite; pinocchio would stop with a RuntimeError later.
    for k in ("ixx", "iyy", "izz"):
        if i[k] < -1e-12:
            raise ModelInputError(f"{path.name}: link '{link.get('name')}' <inertia> {k}: negative ({i[k]:g})")
    smallest = float(np.linalg.eigvalsh(tensor)[0])
    if smallest < -1e-12 * max(1.0, float(np.abs(tensor).max())):
        raise ModelInputError(
            f"{path.name}: link '{link.get('name')}' <inertia>: not positive semi-definite "
            f"(principal moment {smallest:g})"
        )
    return mass, com, rotation @ tensor @ rotation.T


def _check_moves_inertia(
    path: Path,
    chain_joints: list[ET.Element],
    bodies: list[tuple[float, np.ndarray, np.ndarray]],
    rotations: list[np.ndarray],
    translations: list[np.ndarray],
    axes: list[np.ndarray],
) -> None:
    """Refuse a joint that moves no inertia at q = 0 (zero mass and inertia after it): the mass matrix
    would be singular, and the forward dynamics, the laws and pinocchio would divide by zero."""
    world_r, world_p = np.eye(3), np.zeros(3)
    frames = []
    for rotation, translation in zip(rotations, translations, strict=True):  # body frames at q = 0
        world_p, world_r = world_r @ translation + world_p, world_r @ rotation
        frames.append((world_r, world_p))
    for i, joint in enumerate(chain_joints):
        axis, origin = frames[i][0] @ axes[i], frames[i][1]
        moved = 0.0
        for (mass, com, inertia), (r, p) in zip(bodies[i:], frames[i:], strict=True):
            offset = np.cross(axis, r @ com + p - origin)
            moved += float(axis @ r @ inertia @ r.T @ axis) + mass * float(offset @ offset)
        if not moved > 1e-12:
            raise ModelInputError(
                f"{path.name}: joint '{joint.get('name')}' moves no inertia (zero mass and inertia on the links "
                f"after it): the mass matrix would be singular"
            )


def _parse_urdf(path: Path) -> tuple[ET.Element, dict[str, ET.Element], list[ET.Element]]:
    if not path.is_file():
        raise ModelInputError(f"{path}: file not found")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ModelInputError(f"{path.name}: not valid XML ({exc})") from None
    if root.tag != "robot":
        raise ModelInputError(f"{path.name}: root element is <{root.tag}>, expected <robot>")
    links = {link.get("name", ""): link for link in root.findall("link")}
    joints = root.findall("joint")
    for joint in joints:
        for tag in ("parent", "child"):
            if _joint_link(path, joint, tag) not in links:
                raise ModelInputError(f"{path.name}: joint '{joint.get('name')}' <{tag}> names no known link")
    return root, links, joints


def _joint_link(path: Path, joint: ET.Element, tag: str) -> str:
    """The link a joint's ``<parent>`` or ``<child>`` names."""
    element = joint.find(tag)
    link = None if element is None else element.get("link")
    if link is None:
        raise ModelInputError(f"{path.name}: joint '{joint.get('name')}' <{tag}> names no known link")
    return link


def load_robot(name_or_path: str | Path, ee_link: str | None = None) -> RobotModel:
    """Load a built-in robot by name or any serial revolute chain from a URDF file."""
    text = str(name_or_path)
    rate: TorqueRate | None = None  # a URDF path: the default (hil_runtime.rate_limit)
    if text in _BUILTIN:
        path, default_ee, rate = urdf_path(text), _BUILTIN[text][1], _BUILTIN[text][2]
    elif text.endswith(".urdf") or Path(text).is_file():
        path, default_ee = Path(text), None
    else:
        raise ModelInputError(f"robot: unknown name '{text}' (known: {', '.join(robot_names())}, or a .urdf path)")
    root, links, joints = _parse_urdf(path)
    robot = _chain_from_urdf(path, root.get("name", path.stem), links, joints, ee_link or default_ee)
    if text == "ur5_paper":  # Sec. IV-C limits from the parameter file, the URDF's source
        params = yaml.safe_load((DATA_DIR / "ur5_paper.yaml").read_text())
        robot = replace(
            robot,
            position_limit_rad=np.array(params["position_limit_rad"], float),
            position_range_rad=None,
            velocity_limit_rad_s=np.full(robot.n_joints, float(params["velocity_limit_rad_s"])),
            torque_limit_nm=np.array(params["torque_limit_nm"], float),
            gravity_m_s2=np.array([0.0, 0.0, -float(params["gravity_m_s2"])]),
        )
    try:
        return replace(robot, torque_rate_limit_nm_s=torque_rate_limit_nm_s(rate, robot.torque_limit_nm))
    except ValueError as exc:
        raise ModelInputError(f"robots.yaml: {text}: torque_rate: {exc}") from None


def _chain_from_urdf(
    path: Path, name: str, links: dict[str, ET.Element], joints: list[ET.Element], ee_link: str | None
) -> RobotModel:
    child_joint: dict[str, ET.Element] = {}
    for j in joints:
        if j.get("type") in _FLOATING:
            raise ModelInputError(
                f"{path.name}: joint '{j.get('name')}' type '{j.get('type')}': a floating base is not supported "
                "(fix the arm's base link to the world)"
            )
        child = _joint_link(path, j, "child")
        if child in child_joint:  # a URDF is a tree: a second parent closes a loop
            raise ModelInputError(
                f"{path.name}: link '{child}' is the child of joints '{child_joint[child].get('name')}' and "
                f"'{j.get('name')}': a closed chain (only serial arms are supported)"
            )
        child_joint[child] = j
    roots = [link for link in links if link not in child_joint]
    if len(roots) != 1:
        raise ModelInputError(f"{path.name}: expected one root link, found {len(roots)} ({', '.join(roots[:4])})")

    def ancestry(link: str) -> list[ET.Element]:
        chain: list[ET.Element] = []
        while link in child_joint:
            joint = child_joint[link]
            chain.append(joint)
            link = _joint_link(path, joint, "parent")
            if len(chain) > len(joints):
                raise ModelInputError(f"{path.name}: the joint graph has a cycle")
        return chain[::-1]

    def moving(chain: list[ET.Element]) -> list[ET.Element]:
        return [j for j in chain if j.get("type") in _MOVING]

    tip = max(links, key=lambda link: len(moving(ancestry(link))))
    chain_joints = moving(ancestry(tip))
    if not chain_joints:
        raise ModelInputError(f"{path.name}: no revolute joint found")
    # Joints off the chain (a gripper's fingers) are locked at zero. A prismatic joint before the
    # last revolute joint, on the way to the end effector, or continuing the arm serially after it
    # (its parent link has no other child, it mimics nothing) would silently freeze a degree of
    # freedom of the arm, and a later joint-count error would blame another file: refuse it.
    path_to_tip = ancestry(tip)
    on_chain = path_to_tip[: path_to_tip.index(chain_joints[-1])]
    if ee_link is not None and ee_link in links:
        on_chain += ancestry(ee_link)
    children: dict[str, list[ET.Element]] = {}
    for j in joints:
        children.setdefault(_joint_link(path, j, "parent"), []).append(j)
    stack = [_joint_link(path, chain_joints[-1], "child")]
    while stack:
        for j in children.get(stack.pop(), []):
            siblings = children[_joint_link(path, j, "parent")]
            if len(siblings) == 1 and j.find("mimic") is None:
                on_chain.append(j)
            stack.append(_joint_link(path, j, "child"))
    for joint in on_chain:
        if joint.get("type") == "prismatic":
            raise ModelInputError(
                f"{path.name}: joint '{joint.get('name')}' type 'prismatic' on the arm's chain: "
                "only revolute and continuous joints are supported"
            )
    for j in joints:
        if j.get("type") not in _MOVING | {"fixed", "prismatic"}:
            raise ModelInputError(f"{path.name}: joint '{j.get('name')}' type '{j.get('type')}' not supported")

    # Which chain body (0..N-1, or -1 for the base) each link is rigidly part of, and where.
    body_of: dict[str, tuple[int, np.ndarray, np.ndarray]] = {}
    chain_index = {j.get("name"): i for i, j in enumerate(chain_joints)}
    for link in links:
        body, rotation, translation = -1, np.eye(3), np.zeros(3)
        for joint in ancestry(link):
            r, p = _origin(path, joint)
            if joint.get("name") in chain_index:
                body, rotation, translation = chain_index[joint.get("name")], np.eye(3), np.zeros(3)
            else:  # fixed, or a joint off the chain locked at zero
                rotation, translation = rotation @ r, rotation @ p + translation
        body_of[link] = (body, rotation, translation)

    n = len(chain_joints)
    parts: list[list[tuple[float, np.ndarray, np.ndarray]]] = [[] for _ in range(n)]
    for link_name, (body, rotation, translation) in body_of.items():
        if body < 0:
            continue
        mass, com, inertia = _link_inertial(path, links[link_name])
        parts[body].append((mass, rotation @ com + translation, rotation @ inertia @ rotation.T))
    merged = [_combine(p) for p in parts]

    rotations, translations, axes, pos_range, vel_lim, tau_lim = [], [], [], [], [], []
    for i, joint in enumerate(chain_joints):
        parent = _joint_link(path, joint, "parent")
        body, r_parent, p_parent = body_of[parent]
        if body != i - 1:
            raise ModelInputError(f"{path.name}: joint '{joint.get('name')}' breaks the serial chain")
        r, p = _origin(path, joint)
        rotations.append(r_parent @ r)
        translations.append(r_parent @ p + p_parent)
        axis_el = joint.find("axis")
        axis = _floats(path, axis_el, "xyz", "1 0 0", 3) if axis_el is not None else np.array([1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-12:
            raise ModelInputError(f"{path.name}: joint '{joint.get('name')}' <axis> xyz: zero vector")
        axes.append(axis / np.linalg.norm(axis))
        if joint.find("mimic") is not None:  # it would move with another joint, not as its own DOF
            raise ModelInputError(
                f"{path.name}: joint '{joint.get('name')}' <mimic>: a mimic joint on the arm's chain is not supported "
                "(mimic joints off the chain, e.g. fingers, are locked)"
            )
        limit = joint.find("limit")
        if limit is None:  # URDF requires it for revolute; the runtime saturates to effort and velocity
            needs = "lower, upper, effort and velocity" if joint.get("type") == "revolute" else "effort and velocity"
            raise ModelInputError(
                f"{path.name}: joint '{joint.get('name')}' <limit>: missing (a {joint.get('type')} joint needs {needs})"
            )
        for attribute in ("effort", "velocity") + (("lower", "upper") if joint.get("type") == "revolute" else ()):
            if limit.get(attribute) is None:
                raise ModelInputError(f"{path.name}: joint '{joint.get('name')}' <limit> {attribute}: missing")
        lower = float(_floats(path, limit, "lower", "0", 1)[0])
        upper = float(_floats(path, limit, "upper", "0", 1)[0])
        if joint.get("type") == "continuous":  # treated as unbounded in position (docs/robots.md)
            lower, upper = -math.inf, math.inf
        elif lower > upper:
            raise ModelInputError(
                f"{path.name}: joint '{joint.get('name')}' <limit>: lower {lower:g} above upper {upper:g}"
            )
        pos_range.append((lower, upper))
        velocity = float(_floats(path, limit, "velocity", None, 1)[0])
        effort = float(_floats(path, limit, "effort", None, 1)[0])
        if velocity <= 0 or effort <= 0:
            raise ModelInputError(
                f"{path.name}: joint '{joint.get('name')}' <limit>: velocity and effort must be positive"
            )
        vel_lim.append(velocity)
        tau_lim.append(effort)

    _check_moves_inertia(path, chain_joints, merged, rotations, translations, axes)
    ee_rotation, ee_translation = np.eye(3), np.zeros(3)
    if ee_link is not None:
        if ee_link not in body_of or body_of[ee_link][0] != n - 1:
            raise ModelInputError(f"{path.name}: end-effector link '{ee_link}' is not fixed to the last chain body")
        _, ee_rotation, ee_translation = body_of[ee_link]

    return RobotModel(
        name=name,
        urdf_path=path.resolve(),
        joint_names=tuple(j.get("name", f"joint{i}") for i, j in enumerate(chain_joints)),
        joint_rotation=np.array(rotations),
        joint_translation=np.array(translations),
        joint_axis=np.array(axes),
        mass_kg=np.array([m for m, _, _ in merged]),
        com_m=np.array([c for _, c, _ in merged]),
        inertia_kg_m2=np.array([i for _, _, i in merged]),
        ee_rotation=ee_rotation,
        ee_translation=ee_translation,
        position_limit_rad=np.array([min(abs(lo), abs(hi)) if lo <= 0 <= hi else 0.0 for lo, hi in pos_range]),
        position_range_rad=None if all(lo == -hi for lo, hi in pos_range) else np.array(pos_range),
        velocity_limit_rad_s=np.array(vel_lim),
        torque_limit_nm=np.array(tau_lim),
    )
