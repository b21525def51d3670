"""SIMULATED 2-D keypoint detector: the stand-in for the vision network of thesis 5.6.

It projects simulator truth into each camera, adds pixel noise and drops observations that are
outside the frame's readout window (CameraInfo.roi; pixels stay full-image coordinates), behind
the camera, or randomly occluded. It reads ground truth, so it is an option for experiments only
(``detector = "simulated"``); the deployments use the learned detector (learned_detector.py), which
sees only images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# A view whose 21 learned detections of a hand have a median confidence below this does not show
# the hand (the window lost it; chosen on validation sessions 7311 and 7313, not on bench/recon.py's).
HAND_PRESENT_CONFIDENCE = 0.5


@dataclass
class CameraModel:
    P: np.ndarray  # (3,4)
    width: int
    height: int
    roi: tuple[int, int, int, int] | None = None  # window of the full image the frame shows (None: all of it)


def readout_window(info: object) -> tuple[int, int, int, int]:
    """``(x, y, w, h)`` a CameraInfo's image shows of the full image; an all-zero roi means all of it."""
    r = info.roi
    if r.width == 0 or r.height == 0:
        return 0, 0, int(info.width), int(info.height)
    return int(r.x_offset), int(r.y_offset), int(r.width), int(r.height)


@dataclass
class View:
    """One camera's part of a frame set, what an image-based detector reads."""

    camera: str  # "cam0".."cam6"
    model: CameraModel
    image: np.ndarray  # (h, w, 3) uint8 RGB of the readout window (model.roi), not the full image


class SimulatedDetector:
    """``outliers``: the fraction of detections replaced by a wrong pixel anywhere in the window
    (a detector's confusions), which robust triangulation must reject."""

    def __init__(self, pixel_noise: float = 1.0, dropout: float = 0.08, seed: int = 0,
                 outliers: float = 0.0) -> None:
        self.pixel_noise = pixel_noise
        self.dropout = dropout
        self.outliers = outliers
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
            x0, y0, w, h = cam.roi or (0, 0, cam.width, cam.height)  # only what the readout window shows
            inside = (z > 0) & (pix[:, 0] >= x0) & (pix[:, 0] < x0 + w) & (pix[:, 1] >= y0) & (pix[:, 1] < y0 + h)
            kept = self.rng.random(N) >= self.dropout
            if self.outliers > 0:
                wrong = self.rng.random(N) < self.outliers
                pix[wrong] = self.rng.uniform([x0, y0], [x0 + w, y0 + h], (int(wrong.sum()), 2))
            seen[c] = inside & kept & np.isfinite(pix).all(axis=1)
            uv[c] = pix
        if visible is not None:
            seen &= visible.astype(bool)[None, :]
        return uv, seen
