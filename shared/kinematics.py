"""Robot models from URDF: joints, limits, collision primitives, keypoint frames, and forward
kinematics both in numpy and as CasADi expressions (for the trajectory optimizer)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np

ROBOTS_DIR = Path(__file__).parent / "robots"


@dataclass
class Joint:
    name: str
    kind: str  # revolute, continuous, prismatic, fixed
    parent: str
    child: str
    origin: np.ndarray  # 4x4 parent->joint frame
    axis: np.ndarray
    lower: float = -np.inf
    upper: float = np.inf
    velocity: float = np.inf
    effort: float = np.inf
    mimic: str | None = None
    multiplier: float = 1.0
    offset: float = 0.0


@dataclass
class Shape:
    link: str
    kind: str  # box (size = full extents), cylinder (radius, length), sphere (radius)
    origin: np.ndarray  # 4x4 link->shape
    size: np.ndarray


@dataclass
class RobotModel:
    name: str
    joints: list[Joint]
    shapes: list[Shape] = field(default_factory=list)
    root: str = "base"

    @property
    def actuated(self) -> list[Joint]:
        return [j for j in self.joints if j.kind != "fixed" and j.mimic is None]

    @property
    def joint_names(self) -> list[str]:
        """Every moving joint (mimic joints included) in URDF order: the order of JointState."""
        return [j.name for j in self.joints if j.kind != "fixed"]

    @property
    def lower(self) -> np.ndarray:
        return np.array([j.lower for j in self.joints if j.kind != "fixed"])

    @property
    def upper(self) -> np.ndarray:
        return np.array([j.upper for j in self.joints if j.kind != "fixed"])

    @property
    def max_velocity(self) -> np.ndarray:
        return np.array([j.velocity for j in self.joints if j.kind != "fixed"])

    @property
    def max_effort(self) -> np.ndarray:
        return np.array([j.effort for j in self.joints if j.kind != "fixed"])

    def frames(self) -> list[str]:
        return [self.root] + [j.child for j in self.joints]

    def fk(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """Pose (4x4, world) of every link for joint positions in ``joint_names`` order."""
        return _fk(self, np.asarray(q, float), np)

    def fk_casadi(self, q) -> dict[str, tuple]:
        """Same as ``fk`` with a CasADi vector: returns frame -> (R 3x3, p 3x1) expressions."""
        import casadi as ca

        poses = _fk(self, q, ca)
        return {k: (T[:3, :3], T[:3, 3]) for k, T in poses.items()}


def _rpy(r: float, p: float, y: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _origin(el: ET.Element | None) -> np.ndarray:
    T = np.eye(4)
    if el is not None:
        T[:3, 3] = [float(v) for v in el.get("xyz", "0 0 0").split()]
        T[:3, :3] = _rpy(*[float(v) for v in el.get("rpy", "0 0 0").split()])
    return T


def _fk(model: RobotModel, q, lib) -> dict:
    """Generic over numpy and CasADi: only products, sums, sin and cos."""
    names = model.joint_names
    index = {n: i for i, n in enumerate(names)}
    poses = {model.root: np.eye(4) if lib is np else _ca_matrix(np.eye(4))}
    for j in model.joints:
        parent = poses[j.parent]
        T = _mul(parent, j.origin if lib is np else _ca_matrix(j.origin), lib)
        if j.kind != "fixed":
            qi = q[index[j.name]]
            if j.mimic is not None:
                qi = q[index[j.mimic]] * j.multiplier + j.offset
            T = _mul(T, _joint_transform(j, qi, lib), lib)
        poses[j.child] = T
    return poses


def _ca_matrix(M: np.ndarray):
    import casadi as ca

    return ca.DM(M)


def _mul(A, B, lib):
    return A @ B if lib is np else A @ B


def _joint_transform(j: Joint, qi, lib):
    ax = j.axis
    if lib is np:
        T = np.eye(4)
        if j.kind == "prismatic":
            T[:3, 3] = ax * qi
        else:
            c, s = np.cos(qi), np.sin(qi)
            K = np.array([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
            T[:3, :3] = np.eye(3) + s * K + (1 - c) * K @ K
        return T
    import casadi as ca

    if j.kind == "prismatic":
        T = ca.SX.eye(4)
        for r in range(3):
            T[r, 3] = ax[r] * qi
        return T
    c, s = ca.cos(qi), ca.sin(qi)
    K = ca.DM([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
    R = ca.DM.eye(3) + s * K + (1 - c) * (K @ K)
    T = ca.SX.eye(4)
    T[:3, :3] = R
    return T


def parse_urdf(path: str | Path) -> RobotModel:
    root = ET.parse(path).getroot()
    joints = []
    for el in root.findall("joint"):
        limit = el.find("limit")
        mimic = el.find("mimic")
        axis = el.find("axis")
        joints.append(Joint(
            name=el.get("name"), kind=el.get("type"), parent=el.find("parent").get("link"),
            child=el.find("child").get("link"), origin=_origin(el.find("origin")),
            axis=np.array([float(v) for v in (axis.get("xyz") if axis is not None else "1 0 0").split()]),
            lower=float(limit.get("lower", -np.inf)) if limit is not None else -np.inf,
            upper=float(limit.get("upper", np.inf)) if limit is not None else np.inf,
            velocity=float(limit.get("velocity", np.inf)) if limit is not None else np.inf,
            effort=float(limit.get("effort", np.inf)) if limit is not None else np.inf,
            mimic=mimic.get("joint") if mimic is not None else None,
            multiplier=float(mimic.get("multiplier", 1)) if mimic is not None else 1.0,
            offset=float(mimic.get("offset", 0)) if mimic is not None else 0.0))
    # Order joints so parents come first (URDF does not promise it).
    children = {j.child for j in joints}
    roots = [el.get("name") for el in root.findall("link") if el.get("name") not in children]
    ordered, known = [], set(roots)
    pending = list(joints)
    while pending:  # document order, except that a parent always comes before its children
        j = next((j for j in pending if j.parent in known), None)
        if j is None:
            raise ValueError(f"{path}: joints {[j.name for j in pending]} do not connect to the root")
        ordered.append(j)
        known.add(j.child)
        pending.remove(j)
    shapes = []
    for el in root.findall("link"):
        for col in el.findall("collision"):
            geom = col.find("geometry")[0]
            if geom.tag == "box":
                size = [float(v) for v in geom.get("size").split()]
            elif geom.tag == "cylinder":
                size = [float(geom.get("radius")), float(geom.get("length"))]
            elif geom.tag == "sphere":
                size = [float(geom.get("radius"))]
            else:
                continue  # meshes are handled by the collision module when present
            shapes.append(Shape(el.get("name"), geom.tag, _origin(col.find("origin")), np.array(size)))
    return RobotModel(root.get("name"), ordered, shapes, roots[0] if roots else "base")


@cache
def load_robot(name: str) -> RobotModel:
    path = ROBOTS_DIR / f"{name}.urdf"
    if not path.exists():
        known = ", ".join(p.stem for p in ROBOTS_DIR.glob("*.urdf"))
        raise FileNotFoundError(f"no robot model {name!r} (known: {known})")
    return parse_urdf(path)
