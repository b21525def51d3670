"""State representation of the chapter-7 policy (pure numpy).

A state is hand keypoints (2,21,3), object keypoints (K,3), their velocities, tactile (2,6) and
the reservoir activations H. Inputs are translation invariant (thesis 7.2.3): every hand point
relative to its wrist, pairwise translations between wrists, fingertips and object points, and
heights above the table (gravity matters, 7.2.4). Outputs are velocities of every keypoint.
"""

from __future__ import annotations

import numpy as np

from shared.demo import Demo

KEY_POINTS = [0, 4, 8, 12, 16, 20]  # wrist and fingertips: the anchors of the pairwise translations
POS_SCALE = 10.0  # 10 cm -> 1
VEL_SCALE = 5.0  # 0.2 m/s -> 1
TACTILE_SCALE = 0.05  # 20 kPa -> 1


def anchors(hands: np.ndarray, objects: np.ndarray) -> np.ndarray:
    """(..., A, 3): wrists and fingertips of both hands, then object points."""
    lead = hands.shape[:-3]
    return np.concatenate([hands[..., KEY_POINTS, :].reshape(*lead, -1, 3), objects], axis=-2)


def pair_index(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.triu_indices(n, 1)


def state_features(hands: np.ndarray, objects: np.ndarray, hand_vel: np.ndarray, obj_vel: np.ndarray) -> np.ndarray:
    """Feature vector(s) for positions and velocities; leading batch dims allowed."""
    lead = hands.shape[:-3]
    local = (hands - hands[..., :1, :]).reshape(*lead, -1)  # each hand's shape relative to its wrist
    a = anchors(hands, objects)
    i, j = pair_index(a.shape[-2])
    pairs = (a[..., j, :] - a[..., i, :]).reshape(*lead, -1)
    heights = a[..., 2]
    vel = np.concatenate([hand_vel.reshape(*lead, -1), obj_vel.reshape(*lead, -1)], axis=-1)
    return np.concatenate([local * POS_SCALE, pairs * POS_SCALE, heights * POS_SCALE, vel * VEL_SCALE], axis=-1)


def rotate_z(x: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotate points (..., 3) about gravity; ``angle`` broadcasts against x[..., 0]."""
    c, s = np.cos(angle), np.sin(angle)
    out = x.copy()
    out[..., 0] = c * x[..., 0] - s * x[..., 1]
    out[..., 1] = s * x[..., 0] + c * x[..., 1]
    return out


def mirror(demo: Demo) -> Demo:
    """Left/right mirror image (y -> -y) with the hands swapped (thesis 7.6.8)."""
    flip = np.array([1.0, -1.0, 1.0], np.float32)
    meta = dict(demo.meta)
    swap = {"left": "right", "right": "left"}
    for k in ("grasp_hand", "press_hand", "tactile_hand"):
        if k in meta:
            meta[k] = swap[meta[k]]
    meta["mirrored"] = not meta.get("mirrored", False)
    return Demo(dt=demo.dt, hands=demo.hands[:, ::-1] * flip, hand_mask=demo.hand_mask[:, ::-1],
                object_names=demo.object_names, objects=demo.objects * flip, object_mask=demo.object_mask,
                tactile=demo.tactile[:, ::-1], tactile_mask=demo.tactile_mask[:, ::-1], phase=demo.phase, meta=meta)


def velocities(x: np.ndarray, dt: float) -> np.ndarray:
    """Backward differences, zero at the start (what a causal observer sees)."""
    v = np.zeros_like(x)
    v[1:] = (x[1:] - x[:-1]) / dt
    return v


class Reservoir:
    """Linear reservoir of thesis 7.2.8: H_{t+1} = W_R H_t + W_I m V_t, run forwards and backwards."""

    def __init__(self, inputs: int, size: int = 32, radius: float = 0.9, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        q, _ = np.linalg.qr(rng.normal(size=(size, size)))
        self.W_R = radius * q
        self.W_I = rng.normal(0.0, 1.0 / np.sqrt(inputs), (size, inputs))
        self.size = size

    def run(self, v: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """v: (T, inputs) velocities, mask: (T, inputs). Returns H (T, size) = forward + backward."""
        T = len(v)
        drive = (v * mask) @ self.W_I.T
        fwd = np.zeros((T, self.size))
        bwd = np.zeros((T, self.size))
        for t in range(1, T):
            fwd[t] = self.W_R @ fwd[t - 1] + drive[t - 1]
        for t in range(T - 2, -1, -1):
            bwd[t] = self.W_R @ bwd[t + 1] + drive[t + 1]
        return fwd + bwd
