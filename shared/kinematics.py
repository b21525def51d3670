"""Robot models from URDF (pure; files read by yourdfpy and trimesh): joints and limits, collision
shapes per link, keypoint frames, and forward kinematics in numpy and as CasADi expressions (for
the trajectory optimizer).

Joint vectors ``q`` are in ``RobotModel.joint_names`` order: every moving joint in URDF document
order, mimic joints included (the order of JointState). Forward kinematics ignores the q entry of
a mimic joint and uses ``multiplier * q[master] + offset`` instead, as the hardware couples them.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from functools import cache, cached_property
from pathlib import Path

import numpy as np
import trimesh
import yourdfpy

from shared.robots.registry import UnknownRobotError, describe

ROBOTS_DIR = Path(__file__).parent / "robots"
MOVING = ("revolute", "continuous", "prismatic")


class URDFError(ValueError):
    """The URDF is malformed or uses something this parser does not support."""


@dataclass
class Joint:
    name: str
    kind: str  # revolute, continuous, prismatic, fixed
    parent: str
    child: str
    origin: np.ndarray  # 4x4 parent link -> joint frame
    axis: np.ndarray  # unit vector in the joint frame
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
    kind: str  # box (size = full extents), cylinder (radius, length along z), sphere (radius), mesh
    origin: np.ndarray  # 4x4 link -> shape
    size: np.ndarray  # mesh: full extents of its bounding box (vertices are exact)
    mesh: Path | None = None
    vertices: np.ndarray | None = None  # mesh vertices (N,3) in the shape frame, scaled


@dataclass
class RobotModel:
    name: str
    joints: list[Joint]  # document order
    shapes: list[Shape] = field(default_factory=list)
    root: str = "base"
    links: list[str] = field(default_factory=list)
    keypoints: list[str] = field(default_factory=list)  # zero-size links on fixed joints

    @cached_property
    def moving(self) -> list[Joint]:
        return [j for j in self.joints if j.kind in MOVING]

    @property
    def actuated(self) -> list[Joint]:
        """Moving joints that are not mimics: the independent coordinates."""
        return [j for j in self.moving if j.mimic is None]

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.moving]

    @property
    def lower(self) -> np.ndarray:
        return np.array([j.lower for j in self.moving])

    @property
    def upper(self) -> np.ndarray:
        return np.array([j.upper for j in self.moving])

    @property
    def max_velocity(self) -> np.ndarray:
        return np.array([j.velocity for j in self.moving])

    @property
    def max_effort(self) -> np.ndarray:
        return np.array([j.effort for j in self.moving])

    def frames(self) -> list[str]:
        return [self.root] + [j.child for j in self.tree_order]

    @cached_property
    def tree_order(self) -> list[Joint]:
        """Joints with every parent before its children (URDF does not promise it)."""
        ordered, known, pending = [], {self.root}, list(self.joints)
        while pending:
            j = next((j for j in pending if j.parent in known), None)
            if j is None:
                raise URDFError(f"{self.name}: joints {[j.name for j in pending]} do not connect to {self.root}")
            ordered.append(j)
            known.add(j.child)
            pending.remove(j)
        return ordered

    @cached_property
    def coupling(self) -> tuple[np.ndarray, np.ndarray]:
        """(M, c) with q_full = M @ q_actuated + c: how mimic joints follow their masters."""
        names, act = self.joint_names, [j.name for j in self.actuated]
        M, c = np.zeros((len(names), len(act))), np.zeros(len(names))
        for i, j in enumerate(self.moving):
            if j.mimic is None:
                M[i, act.index(j.name)] = 1.0
            else:
                if j.mimic not in act:
                    raise URDFError(f"{j.name} mimics {j.mimic!r}, which is not an independent moving joint")
                M[i, act.index(j.mimic)] = j.multiplier
                c[i] = j.offset
        return M, c

    def couple(self, q: np.ndarray) -> np.ndarray:
        """q with every mimic entry set from its master."""
        q = np.asarray(q, float)
        M, c = self.coupling
        act = [self.joint_names.index(j.name) for j in self.actuated]
        return q[..., act] @ M.T + c

    def fk(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """World pose (4x4) of every link and keypoint frame."""
        q = np.asarray(q, float)
        if q.shape != (len(self.moving),):
            raise ValueError(f"q has shape {q.shape}, expected ({len(self.moving)},)")
        qf = self.couple(q)
        index = {n: i for i, n in enumerate(self.joint_names)}
        poses = {self.root: np.eye(4)}
        for j in self.tree_order:
            T = poses[j.parent] @ j.origin
            if j.kind in MOVING:
                T = T @ _joint_np(j, qf[index[j.name]])
            poses[j.child] = T
        return poses

    def fk_casadi(self, q) -> dict[str, tuple]:
        """Forward kinematics of a CasADi vector (SX, MX or DM): frame -> (R 3x3, p 3x1)."""
        out = self._fk_function(q)
        frames = self.frames()
        return {f: (out[2 * i], out[2 * i + 1]) for i, f in enumerate(frames)}

    @cached_property
    def _fk_function(self):
        import casadi as ca  # heavy (about 0.5 s) and needed only by trajopt's symbolic FK

        q = ca.SX.sym("q", len(self.moving))
        M, c = self.coupling
        act = [self.joint_names.index(j.name) for j in self.actuated]
        qa = ca.vertcat(*[q[i] for i in act]) if act else ca.SX(0, 1)
        qf = ca.mtimes(ca.DM(M), qa) + ca.DM(c)
        index = {n: i for i, n in enumerate(self.joint_names)}
        poses = {self.root: (ca.SX.eye(3), ca.SX.zeros(3))}
        for j in self.tree_order:
            R, p = poses[j.parent]
            p = p + ca.mtimes(R, ca.DM(j.origin[:3, 3]))
            R = ca.mtimes(R, ca.DM(j.origin[:3, :3]))
            if j.kind == "prismatic":
                p = p + ca.mtimes(R, ca.DM(j.axis)) * qf[index[j.name]]
            elif j.kind in MOVING:
                R = ca.mtimes(R, _rotation_ca(j.axis, qf[index[j.name]]))
            poses[j.child] = (R, p)
        outs = []
        for f in self.frames():
            outs += list(poses[f])
        return ca.Function(f"fk_{self.name}", [q], outs)

    def shapes_of(self, link: str) -> list[Shape]:
        return [s for s in self.shapes if s.link == link]


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])


def _joint_np(j: Joint, qi: float) -> np.ndarray:
    T = np.eye(4)
    if j.kind == "prismatic":
        T[:3, 3] = j.axis * qi
    else:
        K = _skew(j.axis)
        T[:3, :3] = np.eye(3) + np.sin(qi) * K + (1 - np.cos(qi)) * K @ K
    return T


def _rotation_ca(axis: np.ndarray, qi):
    import casadi as ca  # heavy: loaded only for symbolic FK

    K = ca.DM(_skew(axis))
    return ca.DM.eye(3) + ca.sin(qi) * K + (1 - ca.cos(qi)) * ca.mtimes(K, K)


def _finite(v, what: str) -> np.ndarray:
    v = np.asarray(v, float)
    if not np.isfinite(v).all():
        raise URDFError(f"{what}: not finite: {v.tolist()}")
    return v


def _limit(value: float | None, default: float) -> float:
    return float(value) if value is not None else default


def load_mesh_vertices(path: Path) -> np.ndarray:
    """Unique vertices (N,3) of a mesh file (STL, OBJ, ... whatever trimesh reads), sorted."""
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises a variety of types for unreadable files
        raise URDFError(f"{path}: unreadable mesh ({exc})") from None
    if len(mesh.vertices) == 0:
        raise URDFError(f"{path}: mesh without vertices")
    return np.unique(np.asarray(mesh.vertices, float), axis=0)


def _resolve_mesh(filename: str, base: Path) -> Path:
    if filename.startswith("package://"):
        filename = filename[len("package://"):].split("/", 1)[-1]
    elif filename.startswith("file://"):
        filename = filename[len("file://"):]
    path = Path(filename)
    return path if path.is_absolute() else base / path


def _shape(link: str, col: yourdfpy.Collision, base: Path) -> Shape:
    g = col.geometry
    origin = _finite(col.origin if col.origin is not None else np.eye(4), f"link {link} collision origin")
    if g.box is not None:
        return Shape(link, "box", origin, _finite(g.box.size, f"link {link} box size"))
    if g.cylinder is not None:
        return Shape(link, "cylinder", origin, _finite([g.cylinder.radius, g.cylinder.length], f"link {link} cylinder"))
    if g.sphere is not None:
        return Shape(link, "sphere", origin, _finite([g.sphere.radius], f"link {link} sphere"))
    if g.mesh is not None:
        path = _resolve_mesh(g.mesh.filename or "", base)
        if not path.exists():
            raise URDFError(f"link {link} mesh: mesh file {path} not found")
        scale = _finite(np.broadcast_to(1.0 if g.mesh.scale is None else g.mesh.scale, (3,)), f"link {link} mesh scale")
        vertices = load_mesh_vertices(path) * scale
        return Shape(link, "mesh", origin, np.ptp(vertices, axis=0), path, vertices)
    raise URDFError(f"link {link}: unsupported collision geometry")


def _joint(j: yourdfpy.Joint) -> Joint:
    if j.type not in MOVING + ("fixed",):
        raise URDFError(f"joint {j.name}: type {j.type!r} is not supported")
    if not j.parent or not j.child:
        raise URDFError(f"joint {j.name}: parent or child missing")
    axis = _finite(j.axis, f"joint {j.name} axis")
    if j.type in MOVING and np.linalg.norm(axis) < 1e-9:
        raise URDFError(f"joint {j.name}: zero axis")
    lim, mim = j.limit, j.mimic
    lower = _limit(lim.lower if lim else None, -np.inf)
    upper = _limit(lim.upper if lim else None, np.inf)
    if j.type == "continuous" or (j.type == "revolute" and lim is None):
        lower, upper = -np.inf, np.inf
    if lower > upper:
        raise URDFError(f"joint {j.name}: lower limit {lower} above upper {upper}")
    return Joint(
        name=j.name, kind=j.type, parent=j.parent, child=j.child,
        origin=_finite(j.origin if j.origin is not None else np.eye(4), f"joint {j.name} origin"),
        axis=axis / max(np.linalg.norm(axis), 1e-12), lower=lower, upper=upper,
        velocity=_limit(lim.velocity if lim else None, np.inf), effort=_limit(lim.effort if lim else None, np.inf),
        mimic=mim.joint if mim is not None else None,
        multiplier=float(mim.multiplier) if mim is not None else 1.0,
        offset=float(mim.offset) if mim is not None else 0.0)


def parse_urdf(path: str | Path) -> RobotModel:
    """The model of a URDF file (read by yourdfpy; meshes by trimesh). Raises URDFError, naming the
    element, for anything malformed or unsupported."""
    path = Path(path)
    try:  # yourdfpy falls back to a forgiving parser on broken XML: refuse it first
        ET.parse(path)
    except ET.ParseError as exc:
        raise URDFError(f"{path}: {exc}") from None
    try:
        robot = yourdfpy.URDF.load(str(path), build_scene_graph=False, load_meshes=False).robot
    except ValueError as exc:
        raise URDFError(f"{path}: a number or number list (origin xyz/rpy, axis xyz, limit, geometry size) "
                        f"is malformed: {exc}") from None
    except (KeyError, AttributeError, TypeError, IndexError) as exc:
        raise URDFError(f"{path}: an element lacks a required attribute or child ({type(exc).__name__}: {exc})") \
            from None
    joints = [_joint(j) for j in robot.joints]
    links = [link.name for link in robot.links]
    children = {j.child for j in joints}
    roots = [n for n in links if n not in children]
    if len(roots) != 1:
        raise URDFError(f"{path}: expected one root link, found {roots}")
    shapes = [_shape(link.name, col, path.parent) for link in robot.links for col in link.collisions]
    fixed_children = {j.child for j in joints if j.kind == "fixed"}
    keypoints = [link.name for link in robot.links if link.name in fixed_children and link.inertial is None
                 and not link.visuals and not link.collisions]
    model = RobotModel(robot.name, joints, shapes, roots[0], links, keypoints)
    model.tree_order  # noqa: B018 - validates connectivity now, not at the first fk call
    model.coupling  # noqa: B018
    return model


@cache
def load_robot(name: str) -> RobotModel:
    """The model of a described robot (shared/robots; cached: treat it as read-only). Raises
    FileNotFoundError for an unknown name, URDFError where the URDF and its description disagree."""
    try:
        desc = describe(name)
    except UnknownRobotError as exc:
        raise FileNotFoundError(str(exc)) from None
    model = parse_urdf(desc.urdf)
    problems = desc.problems(model.joint_names, model.frames(), model.links)
    if problems:
        raise URDFError(f"{name}: the description (shared/robots/{name}.py) disagrees with {desc.urdf.name}: "
                        + "; ".join(problems))
    return model
