"""Per-hand crops for the detector's second stage (pure).

The first stage sees both hands in one small window image and often puts a keypoint of one hand on
the other. The second stage looks at one hand at a time: each hand's centre is the median of the
confident first-stage keypoints, triangulated across the views with outlier rejection, that lie
nearer that hand than the other (``hand_centres``), projected back into every view; the crop
around it spans a fixed metric size at the hand's depth, so which hand a crop shows comes from the
geometry of all views, not from one view's appearance. Left-hand crops are mirrored so that one
network, trained on right-hand-looking crops, serves both hands.
"""

from __future__ import annotations

import cv2
import numpy as np

from services.recon.triangulation import triangulate_robust
from shared.demo import KEYPOINTS_PER_HAND

KEYPOINTS = KEYPOINTS_PER_HAND  # channels of the second stage: one hand's, in MANO/OpenPose order
HALF_SIZE_M = 0.12  # half the crop's side at the hand centre's depth: the fingers' reach plus slack
MIN_PEAKS = 5  # confident first-stage peaks of a hand needed in a view for its centre there
CENTRE_GATE_PX = 12.0  # reprojection gate of the centre's triangulation (the medians are coarse)
TRIANGULATION_GATE_PX = 6.0  # reprojection gate of the keypoints' triangulation (recon's own)
HAND_REACH_M = 0.15  # a keypoint farther than this from a hand's centre is not that hand's
MIN_HAND_SEPARATION_M = 0.03  # centres closer than this are one hand found by both channels


def crop_matrix(centre: np.ndarray, half_px: float, size: int, mirror: bool) -> np.ndarray:
    """2x3 affine map from image pixels to crop pixels (pixel centres at integers): the square of
    half side ``half_px`` around ``centre`` onto ``size`` x ``size``, mirrored left-right on request."""
    s = size / (2.0 * half_px)
    c = (size - 1) / 2.0
    sx = -s if mirror else s
    return np.array([[sx, 0.0, c - sx * centre[0]], [0.0, s, c - s * centre[1]]])


def to_image(uv: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Crop pixels (..., 2) -> image pixels through the inverse of ``M``."""
    Minv = cv2.invertAffineTransform(M)
    return np.asarray(uv, float) @ Minv[:, :2].T + Minv[:, 2]


def focal_px(P: np.ndarray) -> float:
    """The focal length in pixels of a projection matrix (the mean of fx and fy)."""
    K = cv2.decomposeProjectionMatrix(np.asarray(P, float))[0]
    K = K / K[2, 2]
    return float(0.5 * (abs(K[0, 0]) + abs(K[1, 1])))


def _median_centres(P: np.ndarray, uv: np.ndarray, conf: np.ndarray, hands: list[slice],
                    threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Each hand's centre from the medians of its confident peaks per view, triangulated."""
    C = len(P)
    med = np.zeros((C, len(hands), 2))
    seen = np.zeros((C, len(hands)), bool)
    for h, sl in enumerate(hands):
        for c in range(C):
            ok = conf[c, sl] >= threshold
            if ok.sum() >= MIN_PEAKS:
                med[c, h] = np.median(uv[c, sl][ok], axis=0)
                seen[c, h] = True
    points, mask, _ = triangulate_robust(P, med, seen.astype(float), gate_px=CENTRE_GATE_PX)
    return points, mask.astype(bool)


def hand_centres(P: np.ndarray, uv: np.ndarray, conf: np.ndarray, hands: list[slice],
                 threshold: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Each hand's 3-D centre from the first stage's peaks: P (C,3,4), uv (C,N,2) full-image pixels,
    conf (C,N). Returns centres (H,3) and a mask (H,) of the hands found in at least two views.

    The first stage often puts some of one hand's keypoints on the other hand, which drags a
    per-channel median toward the other hand (by 25 mm on average for the worse hand on held-out
    sessions, twice what the second stage was trained to tolerate, and its peaks then follow the
    crop's centre). So every keypoint of both channels is triangulated (RANSAC over the views),
    and each hand's centre is the median of the 3-D keypoints of either channel that lie nearer it
    than the other hand, re-estimated twice; the median of the per-view medians stands in where
    fewer than MIN_PEAKS keypoints triangulate."""
    centres, found = _median_centres(P, uv, conf, hands, threshold)
    rows = np.concatenate([np.arange(sl.start, sl.stop) for sl in hands])
    pts, mask, _ = triangulate_robust(P, uv[:, rows], np.where(conf[:, rows] >= threshold, conf[:, rows], 0.0),
                                      gate_px=TRIANGULATION_GATE_PX)
    mask = mask.astype(bool)
    own = np.repeat(np.arange(len(hands)), [sl.stop - sl.start for sl in hands])
    for h in range(len(hands)):
        mine = mask & (own == h)
        if mine.sum() >= MIN_PEAKS:
            centres[h], found[h] = np.median(pts[mine], axis=0), True
    if len(hands) != 2 or not found.all():
        return centres, found
    seen = pts[mask]
    for _ in range(2):
        d = np.linalg.norm(seen[:, None, :] - centres[None], axis=2)  # (n, 2)
        new = centres.copy()
        for h in range(2):
            near = (d[:, h] < d[:, 1 - h]) & (d[:, h] < HAND_REACH_M)
            if near.sum() >= MIN_PEAKS:
                new[h] = np.median(seen[near], axis=0)
        if np.linalg.norm(new[0] - new[1]) < MIN_HAND_SEPARATION_M:
            break  # both channels on one hand: no second hand to tell apart
        centres = new
    return centres, found


def hand_boxes(P: np.ndarray, centres: np.ndarray, found: np.ndarray, focal: np.ndarray,
               half_m: float = HALF_SIZE_M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per view and hand: the crop centre (C,H,2) in full-image pixels, its half side (C,H) in
    pixels and whether the hand is in front of that camera (C,H)."""
    Xh = np.c_[centres, np.ones(len(centres))]
    proj = np.einsum("cij,hj->chi", P, Xh)
    depth = proj[..., 2] / np.linalg.norm(P[:, None, 2, :3], axis=-1)  # along the optical axis
    ok = found[None, :] & (depth > 0.05)
    centre = proj[..., :2] / np.where(ok, proj[..., 2], 1.0)[..., None]
    half = focal[:, None] * half_m / np.where(ok, depth, 1.0)
    return centre, half, ok
