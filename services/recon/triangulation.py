"""Triangulation of points seen by several calibrated cameras (pure).

``triangulate``: linear (DLT) least squares over the views that see each point.
``triangulate_robust``: the same with outlier rejection across views: every pair of views proposes
a point (RANSAC over all view pairs, vectorised), the proposal with the largest confidence-weighted
inlier support under a reprojection gate wins, and a confidence-weighted DLT over its inliers
refines it. A point with fewer than two inlier views is masked and set to zero, never NaN.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np

from shared.geometry import cross


def _dlt_rows(P: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(C,N,2,4) DLT rows (u*P3 - P1, v*P3 - P2), each normalised so every view counts by its weight
    alone whatever its depth."""
    rows = np.stack([uv[..., 0:1] * P[:, None, 2, :] - P[:, None, 0, :],
                     uv[..., 1:2] * P[:, None, 2, :] - P[:, None, 1, :]], axis=2)
    return rows / np.maximum(np.linalg.norm(rows[..., :3], axis=-1, keepdims=True), 1e-12)


def _solve_normal(A: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least squares of rows A (...,R,4) with X4 = 1, through the 3x3 normal equations
    solved in closed form (vectorised: a batched SVD costs more than the whole rest of the stage).
    Returns (...,3), NaN where the views do not constrain the point."""
    Aw = A * w[..., None]
    M = np.einsum("...ri,...rj->...ij", Aw[..., :3], A[..., :3])
    b = -np.einsum("...ri,...r->...i", Aw[..., :3], A[..., 3])
    adj = np.stack([cross(M[..., 1, :], M[..., 2, :]), cross(M[..., 2, :], M[..., 0, :]),
                    cross(M[..., 0, :], M[..., 1, :])], axis=-1)  # adjugate of a symmetric M
    det = np.einsum("...i,...i->...", M[..., 0, :], adj[..., :, 0])
    scale = np.einsum("...ii->...", M) ** 3
    ok = np.abs(det) > 1e-12 * np.maximum(scale, 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        X = np.einsum("...ij,...j->...i", adj, b) / det[..., None]
    return np.where(ok[..., None], X, np.nan)


def _solve(rows: np.ndarray, w: np.ndarray) -> np.ndarray:
    """rows (C,N,2,4), w (C,N) -> points (N,3) (NaN where fewer views than needed)."""
    C, N = w.shape
    A = rows.transpose(1, 0, 2, 3).reshape(N, 2 * C, 4)
    return _solve_normal(A, np.repeat(w.T, 2, axis=1))


def triangulate(P: np.ndarray, uv: np.ndarray, seen: np.ndarray, min_views: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Linear (DLT) least squares over the views that see each point.

    P: (C,3,4) projection matrices; uv: (C,N,2) pixels; seen: (C,N) bool.
    Returns points (N,3) (NaN where fewer than ``min_views`` saw it) and a mask (N,) uint8.
    """
    points = _solve(_dlt_rows(P, np.nan_to_num(uv)), seen.astype(float))
    ok = seen.sum(axis=0) >= min_views
    points[~ok] = np.nan
    return points, ok.astype(np.uint8)


def project(P: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """points (...,N,3) -> pixels (C,...,N,2) and depths (C,...,N)."""
    Xh = np.concatenate([points, np.ones(points.shape[:-1] + (1,))], axis=-1)
    proj = np.einsum("cij,...nj->c...ni", P, Xh)
    z = proj[..., 2]
    return proj[..., :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[..., None], z


def triangulate_robust(P: np.ndarray, uv: np.ndarray, confidence: np.ndarray, gate_px: float = 6.0,
                       min_views: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Outlier-rejecting triangulation.

    P (C,3,4); uv (C,N,2); confidence (C,N) in [0, 1] (0: not detected; a bool ``seen`` works too).
    Returns points (N,3) (zeros where masked), mask (N,) uint8 and inliers (C,N) bool: the views
    each point was finally triangulated from.
    """
    conf = np.nan_to_num(np.asarray(confidence, float)) * np.isfinite(uv).all(axis=-1)
    uv = np.nan_to_num(uv)
    C, N = conf.shape
    detected = conf > 0
    rows = _dlt_rows(P, uv)
    pairs = list(combinations(range(C), 2))
    if not pairs:
        return np.zeros((N, 3)), np.zeros(N, np.uint8), np.zeros((C, N), bool)
    # One hypothesis per view pair and point: (M,N,3) with M pairs.
    a, b = np.array(pairs).T
    pair_rows = np.stack([rows[a], rows[b]], axis=1)  # (M,2,N,2,4)
    M = len(pairs)
    A = pair_rows.transpose(0, 2, 1, 3, 4).reshape(M, N, 4, 4)
    valid = detected[a] & detected[b]  # (M,N)
    hyp = np.nan_to_num(_solve_normal(A, np.ones((M, N, 4))), nan=1e6)
    pix, z = project(P, hyp)  # (C,M,N,2), (C,M,N)
    err = np.linalg.norm(pix - uv[:, None], axis=-1)
    inl = (err < gate_px) & (z > 0) & detected[:, None]  # (C,M,N)
    # Support: weighted inlier count, ties broken by smaller inlier error.
    score = (inl * conf[:, None]).sum(axis=0) - 1e-3 * (np.where(inl, err, 0.0).sum(axis=0) / gate_px)
    score = np.where(valid & (inl.sum(axis=0) >= 2), score, -np.inf)
    best = np.argmax(score, axis=0)  # (N,)
    inliers = inl[:, best, np.arange(N)]  # (C,N)
    has = np.isfinite(score[best, np.arange(N)])
    inliers &= has[None, :]
    points = _solve(rows, conf * inliers)
    # One re-gating pass: views the refined point explains join, views it does not leave.
    pix, z = project(P, points)
    err = np.linalg.norm(pix - uv, axis=-1)
    regated = detected & (err < gate_px) & (z > 0)
    redo = (regated != inliers).any(axis=0) & (regated.sum(axis=0) >= min_views)
    if redo.any():
        inliers[:, redo] = regated[:, redo]
        points[redo] = _solve(rows[:, redo], (conf * inliers)[:, redo])
    ok = (inliers.sum(axis=0) >= min_views) & np.isfinite(points).all(axis=1)
    points[~ok] = 0.0
    inliers[:, ~ok] = False
    return points, ok.astype(np.uint8), inliers


def reprojection_error(P: np.ndarray, points: np.ndarray, uv: np.ndarray, seen: np.ndarray) -> float:
    """Mean pixel error over the observations used."""
    pix, _ = project(P, points)
    err = np.linalg.norm(pix - uv, axis=-1)
    use = seen & np.isfinite(err)
    return float(err[use].mean()) if use.any() else float("nan")
