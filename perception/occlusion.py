"""Which projected keypoints a camera actually sees: a keypoint is occluded when the line of sight
from the camera centre passes through a hand capsule (as services/world/appearance.py draws the
hands) or hits a physics geom (objects, robot, table) before reaching the point. Pure numpy plus
MuJoCo's ray caster."""

from __future__ import annotations

import mujoco
import numpy as np

HAND_CLEARANCE_M = 0.015  # a hand keypoint sits inside its capsules: stop the ray this far short
OBJECT_CLEARANCE_M = 0.004  # object keypoints lie on the object's surface


def segment_distance(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Shortest distance between segments [p0, p1] and [q0, q1], broadcast over leading axes."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e = np.sum(d1 * d1, -1), np.sum(d2 * d2, -1)
    b, c, f = np.sum(d1 * d2, -1), np.sum(d1 * r, -1), np.sum(d2 * r, -1)
    denom = a * e - b * b
    s = np.where(denom > 1e-12, np.clip((b * f - c * e) / np.where(denom > 1e-12, denom, 1.0), 0, 1), 0.0)
    t = (b * s + f) / np.where(e > 1e-12, e, 1.0)
    t_c = np.clip(t, 0, 1)
    s = np.where((t < 0) | (t > 1), np.clip((b * t_c - c) / np.where(a > 1e-12, a, 1.0), 0, 1), s)
    diff = (p0 + s[..., None] * d1) - (q0 + t_c[..., None] * d2)
    return np.linalg.norm(diff, axis=-1)


def hidden_by_capsules(eye: np.ndarray, points: np.ndarray, clearance: np.ndarray, capsules: list) -> np.ndarray:
    """(N,) True where the sight line eye -> point (shortened by ``clearance``) passes through a
    capsule that does not end at the point itself."""
    if not capsules:
        return np.zeros(len(points), bool)
    a = np.array([c.a for c in capsules])
    b = np.array([c.b for c in capsules])
    radius = np.array([c.radius for c in capsules])
    ray = points - eye
    length = np.linalg.norm(ray, axis=1, keepdims=True)
    end = eye + ray * np.clip((length - clearance[:, None]) / np.maximum(length, 1e-9), 0, 1)
    dist = segment_distance(eye[None, None], end[:, None], a[None], b[None])  # (N, M)
    own = (np.linalg.norm(a[None] - points[:, None], axis=-1) < 1e-6) | \
          (np.linalg.norm(b[None] - points[:, None], axis=-1) < 1e-6)
    return ((dist < radius[None]) & ~own).any(axis=1)


def hidden_by_geoms(model: mujoco.MjModel, data: mujoco.MjData, eye: np.ndarray, points: np.ndarray,
                    clearance: np.ndarray, skip_bodies: set[int]) -> np.ndarray:
    """(N,) True where MuJoCo's ray from the eye hits a geom (of a body not in ``skip_bodies``) short
    of the point by more than ``clearance``."""
    out = np.zeros(len(points), bool)
    geomid = np.zeros(1, np.int32)
    for i, p in enumerate(points):
        vec = p - eye
        length = float(np.linalg.norm(vec))
        if length < 1e-6:
            continue
        start = eye.copy()
        travelled = 0.0
        for _ in range(4):  # step past geoms that do not count (the hands' pose markers)
            d = mujoco.mj_ray(model, data, start, vec / length, None, 1, -1, geomid)
            if d < 0 or travelled + d >= length - clearance[i]:
                break
            if int(model.geom_bodyid[geomid[0]]) not in skip_bodies:
                out[i] = True
                break
            travelled += d + 1e-4
            start = eye + vec / length * travelled
    return out
