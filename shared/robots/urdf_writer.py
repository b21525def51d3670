"""Small helpers the URDF generators share: links with solid-body inertia, joints, keypoint frames,
and convex meshes written by trimesh (kept as code so every dimension lives in one place).

The URDF text is written here, not by yourdfpy: its writer (0.0.60) drops ``<mimic>`` and the
``<mujoco>`` compiler element that both models need."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

HEADER = '<?xml version="1.0"?>\n<robot name="{name}">\n'
MATERIALS = ('  <material name="alu"><color rgba="0.72 0.73 0.76 1"/></material>\n'
             '  <material name="dark"><color rgba="0.2 0.2 0.22 1"/></material>\n'
             '  <material name="steel"><color rgba="0.55 0.57 0.6 1"/></material>\n')

# A shape is (kind, xyz, dims): box dims = full extents (x, y, z); cylinder dims = (radius, length)
# along the local z; sphere dims = (radius,); mesh dims = (filename, half extents for the inertia).
Shape = tuple


def _geometry(kind: str, dims) -> str:
    if kind == "box":
        return f'<box size="{dims[0]:g} {dims[1]:g} {dims[2]:g}"/>'
    if kind == "cylinder":
        return f'<cylinder radius="{dims[0]:g}" length="{dims[1]:g}"/>'
    if kind == "sphere":
        return f'<sphere radius="{dims[0]:g}"/>'
    if kind == "mesh":
        return f'<mesh filename="{dims[0]}"/>'
    raise ValueError(f"unknown shape {kind}")


def _inertia(kind: str, dims, mass: float) -> tuple[float, float, float]:
    """Principal inertia of a solid shape (a mesh uses its bounding box)."""
    if kind == "box" or kind == "mesh":
        x, y, z = dims if kind == "box" else [2 * h for h in dims[1]]
        return (mass * (y * y + z * z) / 12, mass * (x * x + z * z) / 12, mass * (x * x + y * y) / 12)
    if kind == "cylinder":
        r, h = dims
        side = mass * (3 * r * r + h * h) / 12
        return (side, side, mass * r * r / 2)
    r = dims[0]
    return (0.4 * mass * r * r,) * 3


def link(name: str, mass: float, shapes: list[Shape], material: str = "alu", rpy: str = "0 0 0") -> str:
    """A link whose inertia is that of its first shape with all of the mass (good enough for a sim)."""
    out = f'  <link name="{name}">\n'
    if shapes:
        kind, xyz, dims = shapes[0]
        ixx, iyy, izz = (max(v, 1e-7) for v in _inertia(kind, dims, mass))
        out += (f'    <inertial><origin xyz="{xyz}" rpy="{rpy}"/><mass value="{mass:g}"/>\n'
                f'      <inertia ixx="{ixx:.3e}" iyy="{iyy:.3e}" izz="{izz:.3e}" ixy="0" ixz="0" iyz="0"/>'
                '</inertial>\n')
    for kind, xyz, dims in shapes:
        geom = _geometry(kind, dims)
        out += (f'    <visual><origin xyz="{xyz}" rpy="{rpy}"/><geometry>{geom}</geometry>'
                f'<material name="{material}"/></visual>\n')
        out += f'    <collision><origin xyz="{xyz}" rpy="{rpy}"/><geometry>{geom}</geometry></collision>\n'
    return out + "  </link>\n"


def joint(name: str, kind: str, parent: str, child: str, xyz: str, axis: str = "0 0 1", lower: float = 0.0,
          upper: float = 0.0, velocity: float = 0.0, effort: float = 0.0, mimic: str = "",
          rpy: str = "0 0 0") -> str:
    out = (f'  <joint name="{name}" type="{kind}">\n    <parent link="{parent}"/><child link="{child}"/>\n'
           f'    <origin xyz="{xyz}" rpy="{rpy}"/>\n')
    if kind != "fixed":
        out += f'    <axis xyz="{axis}"/>\n'
        out += f'    <limit lower="{lower:g}" upper="{upper:g}" velocity="{velocity:g}" effort="{effort:g}"/>\n'
    if mimic:
        out += f'    <mimic joint="{mimic}" multiplier="1" offset="0"/>\n'
    return out + "  </joint>\n"


def point(name: str, parent: str, xyz: str) -> str:
    """A keypoint frame: a zero-size link on a fixed joint."""
    return f'  <link name="{name}"/>\n' + joint(f"{name}_frame", "fixed", parent, name, xyz)


def frustum(bottom: tuple[float, float], top: tuple[float, float], height: float) -> tuple[np.ndarray, np.ndarray]:
    """A convex box-like frustum: rectangle ``top`` (full x, y) at z=0, ``bottom`` at z=-height.
    Returns vertices (8,3) and outward-wound triangles (12,3)."""
    (bx, by), (tx, ty) = bottom, top
    v = np.array([[-tx / 2, -ty / 2, 0], [tx / 2, -ty / 2, 0], [tx / 2, ty / 2, 0], [-tx / 2, ty / 2, 0],
                  [-bx / 2, -by / 2, -height], [bx / 2, -by / 2, -height], [bx / 2, by / 2, -height],
                  [-bx / 2, by / 2, -height]])
    quads = [(0, 1, 2, 3), (7, 6, 5, 4), (0, 4, 5, 1), (1, 5, 6, 2), (2, 6, 7, 3), (3, 7, 4, 0)]
    tris = []
    for a, b, c, d in quads:
        tris += [(a, b, c), (a, c, d)]
    return v, np.array(tris)


def write_stl(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    """Binary STL (what MuJoCo, coal and most URDF viewers read)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.Trimesh(vertices, triangles, process=False).export(str(path), file_type="stl")


def read_stl(path: Path) -> np.ndarray:
    """Unique vertices (N,3) of an STL file."""
    mesh = trimesh.load(str(path), force="mesh", process=False)
    return np.unique(np.round(np.asarray(mesh.vertices, float), 7), axis=0)
