"""SIMULATED 2-D keypoint detector: the stand-in for the vision network of thesis 5.6.

It projects simulator truth into each camera, adds pixel noise and drops observations that are
outside the image, behind the camera, or randomly occluded. This is the one place outside
evaluation that reads ground truth, and only because no trained detector ships with this build;
a real detector replaces this class and sees only images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class CameraModel:
    P: np.ndarray  # (3,4)
    width: int
    height: int


class SimulatedDetector:
    def __init__(self, pixel_noise: float = 1.0, dropout: float = 0.08, seed: int = 0) -> None:
        self.pixel_noise = pixel_noise
        self.dropout = dropout
        self.rng = np.random.default_rng(seed)

    def detect(self, cameras: list[CameraModel], points: np.ndarray,
               visible: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """points (N,3) world; visible (N,) optional truth occlusion. Returns uv (C,N,2), seen (C,N)."""
        C, N = len(cameras), points.shape[0]
        Xh = np.concatenate([points, np.ones((N, 1))], axis=1)
        uv = np.zeros((C, N, 2))
        seen = np.zeros((C, N), bool)
        for c, cam in enumerate(cameras):
            proj = Xh @ cam.P.T
            z = proj[:, 2]
            pix = proj[:, :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[:, None]
            pix = pix + self.rng.normal(0.0, self.pixel_noise, pix.shape)
            inside = (z > 0) & (pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0) & (pix[:, 1] < cam.height)
            kept = self.rng.random(N) >= self.dropout
            seen[c] = inside & kept & np.isfinite(pix).all(axis=1)
            uv[c] = pix
        if visible is not None:
            seen &= visible.astype(bool)[None, :]
        return uv, seen
