"""The camera calibration's bundle adjustment (calibration/bundle.py, thesis 5.5) as an autolin
residual: the reprojection of a board corner through the board pose and the camera pose into
OpenCV's pinhole camera with 5-coefficient distortion, its pixel error one residual pair.

Parameters per camera: rotation (quaternion, rotation-vector steps), translation, intrinsics as
three vec3 (fx fy cx), (cy k1 k2), (p1 p2 k3); per frame set the board rotation and translation.
Data per observation: the board point and the detected pixel. `from_rotation_vectors` converts
the calibration's rotation-vector unknowns to these arrays and `to_rotation_vectors` back, so
both solvers start from and are compared at the same point.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from . import ops as O
from .trace import Quat, Scalar, Vec3, dot

E1, E2, E3 = [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]
PARAM_TYPES = ["quat", "vec3", "vec3", "vec3", "vec3", "quat", "vec3"]
DATA_TYPES = ["vec3", "scalar", "scalar"]


def reprojection(q_c: Quat, t_c: Vec3, i_a: Vec3, i_b: Vec3, i_c: Vec3, q_b: Quat, t_b: Vec3,
                 obj: Vec3, u: Scalar, v: Scalar) -> tuple:
    """Pixel error of board point `obj` (calibration.bundle.project of cam_T_rig rig_T_board obj)."""
    p = q_c * (q_b * obj + t_b) + t_c
    z = dot(p, E3)
    x, y = dot(p, E1) / z, dot(p, E2) / z
    fx, fy, cx = dot(i_a, E1), dot(i_a, E2), dot(i_a, E3)
    cy, k1, k2 = dot(i_b, E1), dot(i_b, E2), dot(i_b, E3)
    p1, p2, k3 = dot(i_c, E1), dot(i_c, E2), dot(i_c, E3)
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx)
    yd = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy
    return fx * xd + cx - u, fy * yd + cy - v


def reprojection_components(q_c: Any, t_c: Any, i_a: Any, i_b: Any, i_c: Any, q_b: Any, t_b: Any, obj: Any,
                            u: Any, v: Any) -> tuple[Any, Any]:
    """The same residual on component sequences of any arithmetic type (numpy arrays, torch
    tensors, CasADi symbols): the references the traced function is checked and timed against."""
    p = O.vadd(O.qrot(q_c, O.vadd(O.qrot(q_b, obj), t_b)), t_c)
    x, y = p[0] / p[2], p[1] / p[2]
    (fx, fy, cx), (cy, k1, k2), (p1, p2, k3) = i_a, i_b, i_c
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return fx * xd + cx - u, fy * yd + cy - v


@dataclass
class CameraProblem:
    """Parameter arrays (in PARAM_TYPES order), observation data, the index of each parameter
    array per observation, and the gauge (the reference camera's pose held fixed)."""

    params: list[np.ndarray]
    data: list[np.ndarray]
    index: list[np.ndarray]
    fixed: list[np.ndarray | None]


def qexp(v: np.ndarray) -> np.ndarray:
    """Unit quaternions (w first) of rotation vectors (..., 3)."""
    th = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.concatenate([np.cos(th / 2), np.sinc(th / (2 * np.pi)) / 2 * v], axis=-1)


def qlog(q: np.ndarray) -> np.ndarray:
    """Rotation vectors of unit quaternions (..., 4), the inverse of qexp (w >= 0 chosen)."""
    q = q * np.where(q[..., :1] < 0, -1.0, 1.0)
    s = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    th = 2 * np.arctan2(s, q[..., :1])
    return q[..., 1:] * np.where(s > 1e-12, th / np.where(s > 1e-12, s, 1.0), 2.0)


def from_rotation_vectors(intr: np.ndarray, ext: np.ndarray, boards: np.ndarray, reference: int, cam: np.ndarray,
                          frame: np.ndarray, obj: np.ndarray, uv: np.ndarray) -> CameraProblem:
    """intr (cams, 9) fx fy cx cy k1 k2 p1 p2 k3; ext (cams, 6) and boards (frames, 6) rotation
    vector then translation (cam_T_rig and rig_T_board); per observation its camera, frame set,
    board point and pixel."""
    params = [qexp(ext[:, :3]), ext[:, 3:].copy(), intr[:, 0:3].copy(), intr[:, 3:6].copy(), intr[:, 6:9].copy(),
              qexp(boards[:, :3]), boards[:, 3:].copy()]
    gauge = np.arange(len(ext)) == reference
    return CameraProblem(params, [obj, uv[:, 0], uv[:, 1]], [cam] * 5 + [frame] * 2,
                         [gauge, gauge, None, None, None, None, None])


def to_rotation_vectors(params: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(intr, ext, boards) of parameter arrays, the inverse of from_rotation_vectors."""
    intr = np.concatenate(params[2:5], axis=1)
    ext = np.concatenate([qlog(params[0]), params[1]], axis=1)
    return intr, ext, np.concatenate([qlog(params[5]), params[6]], axis=1)

