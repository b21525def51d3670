"""Pure conversions for camera messages."""

from __future__ import annotations

import cv2
import numpy as np


def projection(K: np.ndarray, world_T_cam: np.ndarray) -> np.ndarray:
    """P = K [R | t] mapping world points to pixels (so a reader of CameraInfo.p knows the pose)."""
    cam_T_world = np.linalg.inv(world_T_cam)
    return K @ cam_T_world[:3, :]


def pose_from_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of ``projection``: (K, world_T_cam) from a 3x4 P (RQ decomposition)."""
    K, R, c_h = cv2.decomposeProjectionMatrix(P)[:3]
    K = K / K[2, 2]
    world_T_cam = np.eye(4)
    world_T_cam[:3, :3] = R.T
    world_T_cam[:3, 3] = (c_h[:3] / c_h[3]).ravel()
    return K, world_T_cam


def encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()
