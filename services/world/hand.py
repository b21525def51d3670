"""A kinematic human hand: 21 keypoints (MANO/OpenPose order) from a wrist pose and a few shape
parameters. Dimensions of an adult hand (~18 cm wrist to middle tip)."""

from __future__ import annotations

import numpy as np

# Finger bases (MCP) in the hand frame of a RIGHT hand: x forward (fingers), y toward the thumb
# side, z up out of the back of the hand (palm faces -z).
MCP = {"index": (0.088, 0.026), "middle": (0.092, 0.006), "ring": (0.086, -0.013), "little": (0.078, -0.030)}
SEGMENTS = {"index": (0.040, 0.024, 0.020), "middle": (0.045, 0.028, 0.021), "ring": (0.042, 0.026, 0.020),
            "little": (0.033, 0.019, 0.018)}
THUMB_CMC = np.array([0.022, 0.022, -0.012])
THUMB_SEGMENTS = (0.040, 0.032, 0.028)


def _finger(base: np.ndarray, lengths: tuple, curl: float) -> np.ndarray:
    """Three phalanges, each joint flexed by ``curl`` toward the palm (about the hand's y axis)."""
    angles = curl * np.arange(1, 4)
    steps = np.asarray(lengths)[:, None] * np.stack([np.cos(angles), np.zeros(3), -np.sin(angles)], axis=1)
    return base + np.cumsum(steps, axis=0)


def local_keypoints(curl: np.ndarray, thumb_opposition: float, aperture: float = 0.03) -> np.ndarray:
    """Right-hand keypoints (21,3) in the hand frame.

    curl: flexion per finger (index, middle, ring, little) in radians per joint;
    thumb_opposition: 0 = thumb relaxed beside the hand, 1 = thumb tip opposed to the index tip at
    ``aperture`` metres (a precision grasp). The thumb's inner joints follow a slightly bent curve
    from its base to its tip: a scripted teacher, not an anatomical model.
    """
    pts = np.zeros((21, 3))
    for f, name in enumerate(("index", "middle", "ring", "little")):
        base = np.array([*MCP[name], 0.0])
        pts[5 + 4 * f] = base
        pts[6 + 4 * f: 9 + 4 * f] = _finger(base, SEGMENTS[name], float(curl[f]))
    pts[1] = THUMB_CMC
    relaxed_tip = THUMB_CMC + np.array([0.055, 0.065, -0.035])
    side = np.array([0.0, 1.0, -0.2]) / np.linalg.norm([0.0, 1.0, -0.2])
    opposed_tip = pts[8] + aperture * side
    tip = (1 - thumb_opposition) * relaxed_tip + thumb_opposition * opposed_tip
    bulge = np.array([0.0, 0.012, -0.004])
    for k, frac in ((2, 0.4), (3, 0.72)):
        pts[k] = THUMB_CMC + frac * (tip - THUMB_CMC) + bulge * np.sin(np.pi * frac)
    pts[4] = tip
    return pts


def world_keypoints(side: str, position: np.ndarray, yaw: float, local: np.ndarray, pitch: float = 0.0) -> np.ndarray:
    """Place local keypoints: a left hand is the mirror image (y -> -y) of a right hand; ``pitch``
    tilts the fingers down (rotation about the hand's y axis) before the ``yaw`` about gravity."""
    return local_to_world(side, yaw, pitch, local) + position


def hand_rotation(yaw: float, pitch: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    Ry = np.array([[cp, 0, sp], [0, 1.0, 0], [-sp, 0, cp]])
    return Rz @ Ry


def local_to_world(side: str, yaw: float, pitch: float, local: np.ndarray) -> np.ndarray:
    pts = local.copy()
    if side == "left":
        pts[:, 1] *= -1
    return pts @ hand_rotation(yaw, pitch).T


def pinch_shape() -> np.ndarray:
    """Finger curl of a precision grasp (index slightly bent, others tucked)."""
    return np.array([0.35, 0.6, 0.75, 0.85])


def point_shape() -> tuple[np.ndarray, float]:
    """Index extended, other fingers curled: the pressing hand."""
    return np.array([0.12, 1.1, 1.2, 1.25]), 0.8
