"""An articulated hand: 21 keypoints (MANO/OpenPose order, shared/demo.py) from a wrist pose and
20 joint angles, with per-person bone lengths and palm shape (pure).

Hand frame (a RIGHT hand; a left hand is its mirror image, y -> -y, before the wrist rotation):
origin at the wrist, x toward the middle finger's base, z out of the back of the hand. Each of the
five chains (thumb, index, middle, ring, little) starts at a base point fixed in the palm and has
three bones; its joints are an abduction about the chain frame's z and three flexions about its y
(positive flexion curls toward the palm, -z). Joint limits bound every angle.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from shared.geometry import cross

CHAINS = np.array([[1, 2, 3, 4], [5, 6, 7, 8], [9, 10, 11, 12], [13, 14, 15, 16], [17, 18, 19, 20]])
PALM = np.array([0, 1, 5, 9, 13, 17])  # rigid with the wrist: Kabsch initialises the wrist from these
# Rotation vector, translation, (abduction, 3 flexions) per chain, then the thumb's stretch: the
# thumb's base keypoint is no fixed hinge (its metacarpal slides in the saddle joint), so its three
# "bones" between keypoints may lengthen or shorten by a bounded fraction, held by a prior.
N_JOINTS = 4 * len(CHAINS)
N_PARAMS = 6 + N_JOINTS + 3
STRETCH_LIMIT = 0.25
# Joint limits (rad): (abduction, flexion 1, flexion 2, flexion 3); the thumb's are wider because its
# base frame is only estimated.
FINGER_LIMITS = np.array([[-0.5, 0.5], [-0.5, 1.8], [-0.3, 2.0], [-0.3, 1.8]])
THUMB_LIMITS = np.array([[-1.2, 1.2], [-1.2, 1.6], [-0.8, 1.8], [-0.8, 1.8]])


@dataclass
class HandShape:
    """One person's hand: palm base points (6,3) in the hand frame (rows follow PALM), bone lengths
    (5,3) per chain, and each chain's base frame (5,3,3) (columns: the chain's x, y, z)."""

    palm: np.ndarray
    bones: np.ndarray
    frames: np.ndarray


def joint_bounds() -> tuple[np.ndarray, np.ndarray]:
    lim = np.concatenate([THUMB_LIMITS] + [FINGER_LIMITS] * 4 + [[[-STRETCH_LIMIT, STRETCH_LIMIT]] * 3])
    lo = np.concatenate([np.full(6, -np.inf), lim[:, 0]])
    hi = np.concatenate([np.full(6, np.inf), lim[:, 1]])
    return lo, hi


def rodrigues(r: np.ndarray) -> np.ndarray:
    theta = float(np.sqrt(r @ r))
    if theta < 1e-12:
        return np.eye(3)
    k = r / theta
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * (K @ K)


def rotvec(R: np.ndarray) -> np.ndarray:
    """Inverse of ``rodrigues`` (angles below pi)."""
    cos = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    theta = np.arccos(cos)
    if theta < 1e-9:
        return np.zeros(3)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = np.sin(theta)
    if s < 1e-6:  # near pi: take the axis from the symmetric part
        axis = np.sqrt(np.maximum((np.diag(R) + 1) / 2, 0.0))
        axis *= np.where(np.sign(w) == 0, 1.0, np.sign(w))
        return theta * axis / max(np.linalg.norm(axis), 1e-12)
    return theta * w / (2 * s)


def mirror(side: str) -> np.ndarray:
    return np.diag([1.0, -1.0, 1.0]) if side == "left" else np.eye(3)


def _rot(a: np.ndarray, axis: int) -> np.ndarray:
    """Batched rotations (n,3,3) by angles a (n,) about y (axis 1) or z (axis 2)."""
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((len(a), 3, 3))
    i, j = (0, 2) if axis == 1 else (0, 1)
    k = 3 - i - j
    R[:, k, k] = 1.0
    R[:, i, i] = c
    R[:, j, j] = c
    R[:, i, j] = s if axis == 1 else -s
    R[:, j, i] = -s if axis == 1 else s
    return R


def _chains(shape: HandShape, joints: np.ndarray, stretch: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Chain points (5,4,3) (base, then the three bone ends) in the right-hand frame, each chain's
    abduction axis (5,3) and flexion axis (5,3) (every flexion of a chain turns about the same
    axis: rotations about y keep y), and the bones' directions (5,3,3)."""
    Ra = np.einsum("cij,cjk->cik", shape.frames, _rot(joints[:, 0], 2))
    bones = shape.bones.copy()
    bones[0] *= 1.0 + stretch
    P = np.empty((5, 4, 3))
    dirs = np.empty((5, 3, 3))
    P[:, 0] = shape.palm[1:]
    R = Ra
    for j in range(3):
        R = np.einsum("cij,cjk->cik", R, _rot(joints[:, j + 1], 1))
        dirs[:, j] = R[:, :, 0]
        P[:, j + 1] = P[:, j] + bones[:, j:j + 1] * R[:, :, 0]
    return P, shape.frames[:, :, 2], Ra[:, :, 1], dirs


def local_points(shape: HandShape, joints: np.ndarray, stretch: np.ndarray | None = None) -> np.ndarray:
    """Right-hand keypoints (21,3) in the hand frame for joint angles (5,4) and thumb stretch (3,)."""
    pts = np.empty((21, 3))
    pts[0] = shape.palm[0]
    pts[CHAINS] = _chains(shape, joints, np.zeros(3) if stretch is None else stretch)[0]
    return pts


def forward(shape: HandShape, params: np.ndarray, side: str) -> np.ndarray:
    """World keypoints (21,3): params = [rotation vector (3), wrist position (3), joints (20),
    thumb stretch (3)]."""
    local = local_points(shape, params[6:6 + N_JOINTS].reshape(5, 4), params[6 + N_JOINTS:]) @ mirror(side)
    return local @ rodrigues(params[:3]).T + params[3:6]


def _left_jacobian(r: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian: d/dr of Exp(r) v is -[Exp(r) v]x J_l(r)."""
    theta = float(np.sqrt(r @ r))
    K = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if theta < 1e-6:
        return np.eye(3) + 0.5 * K
    return np.eye(3) + (1 - np.cos(theta)) / theta ** 2 * K + (theta - np.sin(theta)) / theta ** 3 * (K @ K)


def forward_jacobian(shape: HandShape, params: np.ndarray, side: str,
                     base: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World keypoints (21,3) and their Jacobian (21,3,N_PARAMS) with respect to params. With a
    ``base`` rotation, params[:3] is a rotation vector applied on top of it (a solver's local
    parametrisation, away from the rotation vector's wrap-around)."""
    P, z_axis, y_axis, dirs = _chains(shape, params[6:6 + N_JOINTS].reshape(5, 4), params[6 + N_JOINTS:])
    local = np.empty((21, 3))
    local[0] = shape.palm[0]
    local[CHAINS] = P
    Jl = np.zeros((21, 3, N_PARAMS - 6))  # local derivatives, right-hand frame
    rel0 = P[:, 1:] - P[:, :1]  # downstream points about the base
    cols = 4 * np.arange(5)
    Jl[CHAINS[:, 1:], :, cols[:, None]] = cross(z_axis[:, None], rel0)
    Jl[CHAINS[:, 1:], :, cols[:, None] + 1] = cross(y_axis[:, None], rel0)
    Jl[CHAINS[:, 2:], :, cols[:, None] + 2] = cross(y_axis[:, None], P[:, 2:] - P[:, 1:2])
    Jl[CHAINS[:, 3], :, cols + 3] = cross(y_axis, P[:, 3] - P[:, 2])
    for j in range(3):  # a thumb bone's stretch moves every point beyond it along the bone
        Jl[CHAINS[0, j + 1:], :, N_JOINTS + j] = shape.bones[0, j] * dirs[0, j]
    RM = rodrigues(params[:3]) @ (np.eye(3) if base is None else base) @ mirror(side)
    pts = local @ RM.T + params[3:6]
    J = np.empty((21, 3, N_PARAMS))
    rel = pts - params[3:6]
    skew = np.zeros((21, 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -rel[:, 2], rel[:, 1], -rel[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = rel[:, 2], -rel[:, 1], rel[:, 0]
    J[:, :, :3] = -skew @ _left_jacobian(params[:3])
    J[:, :, 3:6] = np.eye(3)
    J[:, :, 6:] = np.einsum("ij,kjp->kip", RM, Jl)
    return pts, J


def palm_frame(points: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (columns x, y, z of the hand frame in the world) and origin from the wrist, index,
    middle and little bases of observed keypoints (21,3)."""
    o = points[0]
    x = points[9] - o
    x /= max(np.linalg.norm(x), 1e-12)
    a, b = points[17] - o, points[5] - o
    z = cross(a, b) if side != "left" else cross(b, a)
    z -= (z @ x) * x
    z /= max(np.linalg.norm(z), 1e-12)
    return np.stack([x, cross(z, x), z], axis=1), o


FRAME_POINTS = np.array([0, 5, 9, 17])  # what palm_frame needs
# An average adult hand (m), for what the initialisation phase never saw (rows follow PALM, CHAINS).
DEFAULT_PALM = np.array([[0.0, 0.0, 0.0], [0.025, 0.020, -0.010], [0.088, 0.025, 0.0], [0.092, 0.005, 0.0],
                         [0.086, -0.013, 0.0], [0.078, -0.030, 0.0]])
DEFAULT_BONES = np.array([[0.045, 0.032, 0.028], [0.040, 0.024, 0.020], [0.045, 0.028, 0.021],
                          [0.042, 0.026, 0.020], [0.033, 0.019, 0.018]])


def estimate_shape(frames: list[np.ndarray], side: str) -> HandShape:
    """A person's shape from frames (each (21,3), NaN where a keypoint was not triangulated; the
    FRAME_POINTS present in each): medians of the palm base points in the hand frame and of the
    bone lengths (what no frame saw comes from DEFAULT_PALM, DEFAULT_BONES); the thumb's base frame
    points along its first bone's median direction."""
    local = []
    for pts in frames:
        R, o = palm_frame(pts, side)
        local.append(((pts - o) @ R) @ mirror(side))
    local = np.stack(local)  # (F,21,3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: filled from the defaults
        med = np.nanmedian(local, axis=0)
        bones = np.nanmedian(np.linalg.norm(np.diff(np.stack(frames)[:, CHAINS], axis=2), axis=-1), axis=0)
    med[PALM] = np.where(np.isfinite(med[PALM]), med[PALM], DEFAULT_PALM)
    bones = np.where(np.isfinite(bones), bones, DEFAULT_BONES)
    frames_out = np.repeat(np.eye(3)[None], 5, axis=0)
    x = med[2] - med[1] if np.isfinite(med[2]).all() else np.array([0.6, 0.7, -0.4])
    x /= max(np.linalg.norm(x), 1e-12)
    z = np.array([0.0, 0.0, 1.0]) - x[2] * x
    z /= max(np.linalg.norm(z), 1e-12)
    frames_out[0] = np.stack([x, cross(z, x), z], axis=1)
    return HandShape(palm=med[PALM], bones=bones, frames=frames_out)


def kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Weighted rotation R and translation t minimising sum w |R src + t - dst|^2."""
    w = np.ones(len(src)) if w is None else np.asarray(w, float)
    w = w / max(w.sum(), 1e-12)
    cs, cd = w @ src, w @ dst
    H = ((src - cs) * w[:, None]).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cd - R @ cs
