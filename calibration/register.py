"""The world frame from the registration board: the board lies on the table at a known place, its
corners (those the bundle adjustment kept) are triangulated from every camera that saw them and
rigidly fitted (Kabsch, once more without the points far off the first fit) to where they lie in
the world. The fit uses the calibrated rig only, so it treats every calibration the
same way (the bench registers aniposelib's rig with it too)."""

from __future__ import annotations

import cv2
import numpy as np

from calibration.detect import Detection

MIN_POINTS = 6  # triangulated corners a registration needs
OUTLIER_FACTOR = 3.0  # points farther than this times the median fit residual are refitted without
MIN_OUTLIER_M = 0.0005  # never drop points closer than this to the fit


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rigid dst_T_src (4x4) minimising the squared distances of paired points (N,3)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    T = np.eye(4)
    T[:3, :3] = Vt.T @ D @ U.T
    T[:3, 3] = cd - T[:3, :3] @ cs
    return T


def triangulate(views: list[Detection], K: list[np.ndarray], dist: list[np.ndarray],
                cam_T_rig: list[np.ndarray]) -> dict[int, np.ndarray]:
    """Corner id -> rig point (linear triangulation of undistorted rays) for corners seen twice or more."""
    rows: dict[int, list[np.ndarray]] = {}
    for v in views:
        P = cam_T_rig[v.camera][:3]
        xy = cv2.undistortPoints(v.corners.reshape(-1, 1, 2), K[v.camera], dist[v.camera]).reshape(-1, 2)
        for i, (x, y) in zip(v.ids, xy, strict=True):
            rows.setdefault(int(i), []).extend([x * P[2] - P[0], y * P[2] - P[1]])
    out = {}
    for i, r in rows.items():
        if len(r) >= 4:
            X = np.linalg.svd(np.array(r))[2][-1]
            out[i] = X[:3] / X[3]
    return out


def world_T_rig(views: list[Detection], K: list, dist: list, cam_T_rig: list, board_points: np.ndarray,
                world_T_board: np.ndarray) -> np.ndarray | None:
    """The registration, or None when fewer than MIN_POINTS corners could be triangulated."""
    pts = triangulate(views, K, dist, cam_T_rig)
    if len(pts) < MIN_POINTS:
        return None
    ids = sorted(pts)
    world = board_points[ids] @ world_T_board[:3, :3].T + world_T_board[:3, 3]
    rig = np.array([pts[i] for i in ids])
    T = kabsch(rig, world)
    # a corner half hidden (by the robot, an object) can triangulate off the board: fit again without
    err = np.linalg.norm(rig @ T[:3, :3].T + T[:3, 3] - world, axis=1)
    keep = err <= max(OUTLIER_FACTOR * np.median(err), MIN_OUTLIER_M)
    return kabsch(rig[keep], world[keep]) if keep.sum() >= MIN_POINTS else T
