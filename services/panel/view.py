"""Messages -> drawable arrays for the dashboard (pure: no viser, no Zenoh)."""

from __future__ import annotations

import numpy as np
from matplotlib import colormaps

from shared.kinematics import RobotModel

# MANO/OpenPose bones: wrist to each finger base, then along each finger.
BONES = [(0, 1), (1, 2), (2, 3), (3, 4)] + [
    pair for b in (5, 9, 13, 17) for pair in ((0, b), (b, b + 1), (b + 1, b + 2), (b + 2, b + 3))]
HAND_COLORS = {"left": (230, 120, 90), "right": (90, 120, 230)}
DIM = 0.35  # brightness of unobserved keypoints


def hand_segments(hand: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(B,2,3) bone segments and a per-segment brightness (1 observed, DIM when an end is masked)."""
    idx = np.array(BONES)
    seg = hand[idx]
    seen = np.ones(len(idx)) if mask is None else np.where(mask[idx].all(axis=1), 1.0, DIM)
    return seg, seen


def segment_colors(base: tuple[int, int, int], brightness: np.ndarray) -> np.ndarray:
    c = np.asarray(base, float)[None, None, :] * brightness[:, None, None]
    return np.repeat(c, 2, axis=1).astype(np.uint8)


def tactile_image(pressure: np.ndarray, mask: np.ndarray | None = None, vmax: float = 30.0,
                  scale: int = 12) -> np.ndarray:
    """16x16 pressure (kPa) -> an RGB heatmap image, unpopulated cells dark grey."""
    p = np.clip(np.asarray(pressure, float).reshape(16, 16) / vmax, 0.0, 1.0)
    rgb = (colormaps["inferno"](p)[..., :3] * 255).astype(np.uint8)
    if mask is not None:
        rgb[np.asarray(mask).reshape(16, 16) == 0] = (40, 40, 40)
    return np.kron(rgb, np.ones((scale, scale, 1), np.uint8))


def link_boxes(model: RobotModel, q: np.ndarray) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, dimensions, world 4x4 pose) per collision shape; cylinders drawn as their bounding box."""
    poses = model.fk(q)
    out = []
    for i, s in enumerate(model.shapes):
        dims = s.size if s.kind == "box" else (np.array([2 * s.size[0]] * 2 + [s.size[1]]) if s.kind == "cylinder"
                                                 else np.full(3, 2 * s.size[0]))
        out.append((f"{s.link}_{i}", dims, poses[s.link] @ s.origin))
    return out


def object_colors(names: list[str]) -> np.ndarray:
    """One colour per object (the part before '/')."""
    objects = sorted({n.split("/")[0] for n in names})
    palette = (np.array(colormaps["tab10"](np.linspace(0, 1, 10))[:, :3]) * 255).astype(np.uint8)
    return np.array([palette[objects.index(n.split("/")[0]) % 10] for n in names]).reshape(-1, 3)
