"""Least-squares triangulation of points seen by several calibrated cameras (pure)."""

from __future__ import annotations

import numpy as np


def triangulate(P: np.ndarray, uv: np.ndarray, seen: np.ndarray, min_views: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Linear (DLT) least squares over the views that see each point.

    P: (C,3,4) projection matrices; uv: (C,N,2) pixels; seen: (C,N) bool.
    Returns points (N,3) (NaN where fewer than ``min_views`` saw it) and a mask (N,) uint8.
    """
    C, N = seen.shape
    # Each view contributes two rows per point: u*P3 - P1, v*P3 - P2.
    rows_u = uv[..., 0:1] * P[:, None, 2, :] - P[:, None, 0, :]  # (C,N,4)
    rows_v = uv[..., 1:2] * P[:, None, 2, :] - P[:, None, 1, :]
    A = np.concatenate([rows_u, rows_v], axis=0)  # (2C,N,4)
    w = np.concatenate([seen, seen], axis=0).astype(float)  # weights zero out unseen views
    # Normalize rows so every view counts equally whatever its depth.
    A = A / np.maximum(np.linalg.norm(A[..., :3], axis=-1, keepdims=True), 1e-12)
    A = A * w[..., None]
    A = np.transpose(A, (1, 0, 2))  # (N,2C,4)
    _, _, vt = np.linalg.svd(A)
    X = vt[:, -1, :]
    points = X[:, :3] / np.where(np.abs(X[:, 3:4]) < 1e-12, np.nan, X[:, 3:4])
    ok = seen.sum(axis=0) >= min_views
    points[~ok] = np.nan
    return points, ok.astype(np.uint8)


def reprojection_error(P: np.ndarray, points: np.ndarray, uv: np.ndarray, seen: np.ndarray) -> float:
    """Mean pixel error over the observations used."""
    Xh = np.concatenate([points, np.ones((points.shape[0], 1))], axis=1)
    proj = np.einsum("cij,nj->cni", P, Xh)
    pix = proj[..., :2] / proj[..., 2:3]
    err = np.linalg.norm(pix - uv, axis=-1)
    use = seen & np.isfinite(err)
    return float(err[use].mean()) if use.any() else float("nan")
