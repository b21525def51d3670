"""Small geometry helpers shared by services (pure)."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.cross for 3-vectors along the last axis, broadcast; bit-identical to it and about twice as
    fast on the small arrays of recon's inner loops (np.cross pays for moving axes each call)."""
    a, b = np.broadcast_arrays(np.asarray(a), np.asarray(b))
    out = np.empty(a.shape, np.result_type(a, b))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def projection(K: np.ndarray, world_T_cam: np.ndarray) -> np.ndarray:
    """P = K [R | t] mapping world points to pixels (CameraInfo.p carries the pose this way)."""
    return K @ np.linalg.inv(world_T_cam)[:3, :]


def pose_from_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of ``projection``: (K, world_T_cam) from a 3x4 P (RQ decomposition)."""
    K, R, c_h = cv2.decomposeProjectionMatrix(np.asarray(P, float).reshape(3, 4))[:3]
    K = K / K[2, 2]
    world_T_cam = np.eye(4)
    world_T_cam[:3, :3] = R.T
    world_T_cam[:3, 3] = (c_h[:3] / c_h[3]).ravel()
    return K, world_T_cam


def wxyz(R: np.ndarray) -> np.ndarray:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def look_at(eye: np.ndarray, target: np.ndarray, up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera pose (4x4, OpenCV axes: x right, y down, z forward) at ``eye`` looking at ``target``."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T
