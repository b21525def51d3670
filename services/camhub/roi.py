"""Per-camera regions of interest that follow the hands (thesis 5.4), pure.

Each trigger reads out, per camera, the window around the last reconstructed hand keypoints plus a
margin, so the hands are seen at full sensor resolution while the rig keeps its rate. When no hand
is tracked (no recent scene, too few keypoints, hands outside a camera's view) that camera reads
the full frame, and so it does every ``reacquire_every`` triggers, so a hand entering the cell
outside the current windows is found again; while one hand is missing from the scene (it left its
window, or moves too fast for the margin) every ``reacquire_lost_every``-th trigger reads full
frames instead. Windows start on even pixels and have even sizes, as
sensor readout windows do (MT9P001).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

MIN_POINTS = 3  # keypoints of the scene needed before a window is trusted


class Roi(NamedTuple):
    """A readout window in full-image pixels (``sensor_msgs/RegionOfInterest`` order)."""
    x_offset: int
    y_offset: int
    width: int
    height: int


@dataclass(frozen=True)
class RoiParams:
    margin_m: float = 0.08  # around every keypoint: finger extent plus hand motion over a frame or two
    min_px: int = 64  # smallest window side
    max_age_s: float = 0.5  # a scene older than this counts as tracking lost
    reacquire_every: int = 10  # every n-th trigger reads full frames (0: never)
    reacquire_lost_every: int = 2  # the same while a hand is missing from the scene (0: as reacquire_every)


def full_frame(width: int, height: int) -> Roi:
    return Roi(0, 0, width, height)


def project(points: np.ndarray, K: np.ndarray, dist: np.ndarray, world_T_cam: np.ndarray) -> tuple[np.ndarray,
                                                                                                    np.ndarray]:
    """Pixels (N,2) of world points (N,3) and their depths (N,) along the optical axis."""
    pts = np.asarray(points, float).reshape(-1, 3)
    cam_T_world = np.linalg.inv(world_T_cam)
    depth = pts @ cam_T_world[2, :3] + cam_T_world[2, 3]
    if len(pts) == 0:
        return np.zeros((0, 2)), depth
    rvec, _ = cv2.Rodrigues(cam_T_world[:3, :3])
    uv, _ = cv2.projectPoints(pts, rvec, cam_T_world[:3, 3], np.asarray(K, float), np.asarray(dist, float))
    return uv.reshape(-1, 2), depth


def window_around(uv: np.ndarray, depth: np.ndarray, fx: float, width: int, height: int,
                  params: RoiParams) -> Roi | None:
    """The even-aligned window holding every point in front of the camera plus ``margin_m`` (in
    pixels at each point's depth), clipped to the image; None when no point lands near the image."""
    front = depth > 1e-3
    if not front.any():
        return None
    uv, depth = uv[front], depth[front]
    pad = fx * params.margin_m / depth
    lo = np.min(uv - pad[:, None], axis=0)
    hi = np.max(uv + pad[:, None], axis=0)
    if hi[0] < 0 or hi[1] < 0 or lo[0] > width - 1 or lo[1] > height - 1:
        return None  # the hands are outside this camera's view
    return fit_window(lo, hi, width, height, params.min_px)


def fit_window(lo: np.ndarray, hi: np.ndarray, width: int, height: int, min_px: int) -> Roi:
    """Pixel box [lo, hi] (inclusive corners, may exceed the image) -> an even-aligned window of at
    least ``min_px`` per side inside a ``width`` x ``height`` image."""
    out = []
    for a, b, size in ((lo[0], hi[0], width), (lo[1], hi[1], height)):
        start, stop = int(np.floor(max(a, 0))), int(np.ceil(min(b, size - 1))) + 1  # [start, stop) to keep
        side = max(stop - start, min(min_px, size))
        start = int(np.clip((start + stop - side) // 2, 0, max(size - side, 0)))
        if start % 2:  # even start: move left one pixel and grow by two, keeping the right edge covered
            start, side = start - 1, side + 2
        side += side % 2
        side = min(side, size - start)
        side -= side % 2 if start + side < size else 0  # odd only where it ends on an odd image's edge
        out.append((start, side))
    (x, w), (y, h) = out
    return Roi(x, y, w, h)


@dataclass(frozen=True)
class CameraGeometry:
    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    world_T_cam: np.ndarray


def rig_windows(cameras: list[CameraGeometry], points: np.ndarray | None, scene_age_s: float, trigger: int,
                params: RoiParams, hand_missing: bool = False) -> tuple[dict[str, Roi], bool]:
    """Windows of one trigger for every camera, and whether the hands are tracked.

    ``points`` are the tracked hand keypoints (N,3) of the last scene (masked ones left out);
    ``hand_missing``: that scene lacks one of the hands (``missing_hand``)."""
    tracked = points is not None and len(points) >= MIN_POINTS and scene_age_s <= params.max_age_s
    every = params.reacquire_lost_every if hand_missing and params.reacquire_lost_every > 0 else \
        params.reacquire_every
    reacquire = every > 0 and trigger % every == 0
    out = {}
    for cam in cameras:
        window = None
        if tracked and not reacquire:
            uv, depth = project(points, cam.K, cam.dist, cam.world_T_cam)
            window = window_around(uv, depth, float(cam.K[0, 0]), cam.width, cam.height, params)
        out[cam.name] = window or full_frame(cam.width, cam.height)
    return out, tracked


def tracked_points(hand_keypoints: np.ndarray, hand_mask: np.ndarray) -> np.ndarray:
    """The observed hand keypoints (N,3) of a Scene's flat fields (an empty mask: all observed)."""
    pts = np.asarray(hand_keypoints, float).reshape(-1, 3)
    mask = np.asarray(hand_mask, bool).ravel()
    if mask.size == 0:
        mask = np.ones(len(pts), bool)
    if mask.size != len(pts):
        raise ValueError(f"hand_mask has {mask.size} entries for {len(pts)} keypoints")
    keep = mask & np.all(np.isfinite(pts), axis=1)
    return pts[keep]


def missing_hand(hand_mask: np.ndarray, hands: int) -> bool:
    """Whether a scene's flat hand mask (hands x keypoints) has a hand with fewer than MIN_POINTS
    observed keypoints (an empty mask: every keypoint observed)."""
    mask = np.asarray(hand_mask, bool).ravel()
    if mask.size == 0 or hands <= 0:
        return False
    if mask.size % hands:
        raise ValueError(f"hand_mask has {mask.size} entries, not a multiple of {hands} hands")
    return bool((mask.reshape(hands, -1).sum(axis=1) < MIN_POINTS).any())


def crop(image: np.ndarray, roi: Roi) -> np.ndarray:
    """The window of a full frame (sources that read whole frames: devices, files)."""
    x, y, w, h = roi
    return image[y:y + h, x:x + w]


def to_full_image(uv: np.ndarray, roi: Roi) -> np.ndarray:
    """Pixels of a window image -> pixels of the full image (what a detector on ROI crops reports)."""
    return np.asarray(uv, float) + [roi.x_offset, roi.y_offset]
