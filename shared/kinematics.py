"""Robot models from URDF (pure): joints and limits, collision shapes per link, keypoint frames, and
forward kinematics in numpy and as CasADi expressions (for the trajectory optimizer).

Joint vectors ``q`` are in ``RobotModel.joint_names`` order: every moving joint in URDF document
order, mimic joints included (the order of JointState). Forward kinematics ignores the q entry of
a mimic joint and uses ``multiplier * q[master] + offset`` instead, as the hardware couples them.
"""

from __future__ import annotations

import struct
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from functools import cache, cached_property
from pathlib import Path

import numpy as np

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
        import casadi as ca

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
    import casadi as ca

    K = ca.DM(_skew(axis))
    return ca.DM.eye(3) + ca.sin(qi) * K + (1 - ca.cos(qi)) * ca.mtimes(K, K)


def rpy_matrix(r: float, p: float, y: float) -> np.ndarray:
    """URDF fixed-axis roll, pitch, yaw: R = Rz(y) Ry(p) Rx(r)."""
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _floats(text: str | None, n: int, what: str) -> np.ndarray:
    try:
        v = np.array([float(x) for x in (text or "").split()])
    except ValueError:
        raise URDFError(f"{what}: {text!r} is not a list of numbers") from None
    if v.shape != (n,) or not np.isfinite(v).all():
        raise URDFError(f"{what}: expected {n} finite numbers, got {text!r}")
    return v


def _origin(el: ET.Element | None, what: str) -> np.ndarray:
    T = np.eye(4)
    if el is not None:
        T[:3, 3] = _floats(el.get("xyz", "0 0 0"), 3, f"{what} origin xyz")
        T[:3, :3] = rpy_matrix(*_floats(el.get("rpy", "0 0 0"), 3, f"{what} origin rpy"))
    return T


def _limit(el: ET.Element | None, key: str, default: float) -> float:
    return float(el.get(key, default)) if el is not None else default


def load_mesh_vertices(path: Path) -> np.ndarray:
    """Vertices (N,3) of a binary/ASCII STL or an OBJ file."""
    data = path.read_bytes()
    if path.suffix.lower() == ".obj":
        pts = [line.split()[1:4] for line in data.decode().splitlines() if line.startswith("v ")]
        return np.array(pts, float)
    if data[:5].lower() == b"solid" and b"facet" in data[:300]:
        pts = [line.split()[1:4] for line in data.decode().splitlines() if line.strip().startswith("vertex")]
        return np.unique(np.array(pts, float), axis=0)
    count = struct.unpack_from("<I", data, 80)[0]
    if len(data) < 84 + 50 * count:
        raise URDFError(f"{path}: truncated binary STL")
    raw = np.frombuffer(data, dtype=np.dtype([("n", "<3f4"), ("v", "<9f4"), ("a", "<u2")]), count=count, offset=84)
    return np.unique(raw["v"].reshape(-1, 3).astype(float), axis=0)


def _resolve_mesh(filename: str, base: Path) -> Path:
    if filename.startswith("package://"):
        filename = filename[len("package://"):].split("/", 1)[-1]
    elif filename.startswith("file://"):
        filename = filename[len("file://"):]
    path = Path(filename)
    return path if path.is_absolute() else base / path


def _shape(link: str, col: ET.Element, base: Path) -> Shape | None:
    geom = col.find("geometry")
    if geom is None or len(geom) == 0:
        raise URDFError(f"link {link}: collision without geometry")
    g = geom[0]
    origin = _origin(col.find("origin"), f"link {link} collision")
    what = f"link {link} {g.tag}"
    if g.tag == "box":
        return Shape(link, "box", origin, _floats(g.get("size"), 3, what))
    if g.tag == "cylinder":
        return Shape(link, "cylinder", origin, np.array([float(g.get("radius")), float(g.get("length"))]))
    if g.tag == "sphere":
        return Shape(link, "sphere", origin, np.array([float(g.get("radius"))]))
    if g.tag == "mesh":
        path = _resolve_mesh(g.get("filename", ""), base)
        if not path.exists():
            raise URDFError(f"{what}: mesh file {path} not found")
        scale = _floats(g.get("scale", "1 1 1"), 3, f"{what} scale")
        vertices = load_mesh_vertices(path) * scale
        return Shape(link, "mesh", origin, np.ptp(vertices, axis=0), path, vertices)
    raise URDFError(f"{what}: unsupported collision geometry")


def parse_urdf(path: str | Path) -> RobotModel:
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise URDFError(f"{path}: {exc}") from None
    joints = []
    for el in root.findall("joint"):
        name, kind = el.get("name"), el.get("type")
        if kind not in MOVING + ("fixed",):
            raise URDFError(f"joint {name}: type {kind!r} is not supported")
        parent, child = el.find("parent"), el.find("child")
        if parent is None or child is None:
            raise URDFError(f"joint {name}: parent or child missing")
        axis = _floats(el.find("axis").get("xyz"), 3, f"joint {name} axis") if el.find("axis") is not None \
            else np.array([1.0, 0.0, 0.0])
        if kind in MOVING and np.linalg.norm(axis) < 1e-9:
            raise URDFError(f"joint {name}: zero axis")
        lim, mim = el.find("limit"), el.find("mimic")
        lower, upper = _limit(lim, "lower", -np.inf), _limit(lim, "upper", np.inf)
        if kind == "continuous" or (kind == "revolute" and lim is None):
            lower, upper = -np.inf, np.inf
        if lower > upper:
            raise URDFError(f"joint {name}: lower limit {lower} above upper {upper}")
        joints.append(Joint(
            name=name, kind=kind, parent=parent.get("link"), child=child.get("link"),
            origin=_origin(el.find("origin"), f"joint {name}"), axis=axis / max(np.linalg.norm(axis), 1e-12),
            lower=lower, upper=upper, velocity=_limit(lim, "velocity", np.inf), effort=_limit(lim, "effort", np.inf),
            mimic=mim.get("joint") if mim is not None else None,
            multiplier=float(mim.get("multiplier", 1)) if mim is not None else 1.0,
            offset=float(mim.get("offset", 0)) if mim is not None else 0.0))
    links = [el.get("name") for el in root.findall("link")]
    children = {j.child for j in joints}
    roots = [n for n in links if n not in children]
    if len(roots) != 1:
        raise URDFError(f"{path}: expected one root link, found {roots}")
    shapes = []
    for el in root.findall("link"):
        for col in el.findall("collision"):
            shapes.append(_shape(el.get("name"), col, path.parent))
    fixed_children = {j.child for j in joints if j.kind == "fixed"}
    keypoints = [el.get("name") for el in root.findall("link") if len(el) == 0 and el.get("name") in fixed_children]
    model = RobotModel(root.get("name", path.stem), joints, shapes, roots[0], links, keypoints)
    model.tree_order  # noqa: B018 - validates connectivity now, not at the first fk call
    model.coupling  # noqa: B018
    return model


@cache
def load_robot(name: str) -> RobotModel:
    """A model from shared/robots/<name>.urdf (cached: treat it as read-only)."""
    path = ROBOTS_DIR / f"{name}.urdf"
    if not path.exists():
        known = ", ".join(p.stem for p in ROBOTS_DIR.glob("*.urdf"))
        raise FileNotFoundError(f"no robot model {name!r} (known: {known})")
    return parse_urdf(path)
