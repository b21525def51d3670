"""Rigid objects posed from their 2-D detections in every view (pure).

The task defines each object's keypoints in its own frame, so an object has six unknowns however
many of its keypoints the views detect. Its pose is the one whose projected keypoints best match
the detections of all views at once (reprojection error, a robust Cauchy loss, scipy's
``least_squares`` with an analytic Jacobian), which uses single-view detections that triangulation
cannot and lets a wrong detection (a keypoint put on a neighbouring corner, on the other object or
on a hand) count little. Start poses compete (RANSAC over hypotheses): the previous pose, the
Kabsch fit of the triangulated keypoints and Kabsch fits of triples of them; the one under which
most detections reproject within the gate wins and is refined.

While an object rests, its frame sets accumulate in a window (up to ``window`` of them) and the
pose is fitted to all their detections together, which averages the detector's per-frame errors;
a frame set whose detections the window's pose no longer explains (the object moved) restarts
the window with that frame set alone.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from services.recon.hand_model import kabsch, rodrigues

GATE_PX = 6.0  # a detection within this of the pose's projection is an inlier
CAUCHY_PX = 2.5  # the robust loss's scale: residuals beyond it count less and less
MIN_DETECTIONS = 4  # confident detections (over views and keypoints) a frame set needs for a pose
MIN_VIEWS = 2  # ... in this many views at least


def _skew(v: np.ndarray) -> np.ndarray:
    """(n,3) -> (n,3,3) cross-product matrices."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], -1), np.stack([v[:, 2], z, -v[:, 0]], -1),
                     np.stack([-v[:, 1], v[:, 0], z], -1)], 1)


def reprojection(P: np.ndarray, model: np.ndarray, R: np.ndarray, t: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Pixel distance (V,k) of each view's detection from the projection of the posed keypoint
    (inf behind a camera). P (V,3,4), model (k,3), uv (V,k,2)."""
    X = model @ R.T + t
    x = np.einsum("vij,kj->vki", P[:, :, :3], X) + P[:, None, :, 3]
    z = x[..., 2]
    pix = x[..., :2] / np.where(np.abs(z) > 1e-9, z, 1e-9)[..., None]
    return np.where(z > 1e-6, np.linalg.norm(pix - uv, axis=-1), np.inf)


@dataclass
class PoseFit:
    R: np.ndarray
    t: np.ndarray
    inliers: np.ndarray  # (V,k) detections within the gate
    rms_px: float  # over the inliers

    def points(self, model: np.ndarray) -> np.ndarray:
        return model @ self.R.T + self.t


def refine(P: np.ndarray, model: np.ndarray, uv: np.ndarray, w: np.ndarray, R0: np.ndarray, t0: np.ndarray,
           scale_px: float = CAUCHY_PX, max_nfev: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Robust reprojection fit of one rigid pose: P (V,3,4), model (k,3), uv (V,k,2), w (V,k)
    weights (0: no detection). The rotation is solved as a correction of R0."""
    v_idx, k_idx = np.nonzero(w > 0)
    sw = np.sqrt(w[v_idx, k_idx])[:, None]
    Pv, target, local = P[v_idx], uv[v_idx, k_idx], model[k_idx]

    def parts(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        R = rodrigues(x[:3]) @ R0
        arm = local @ R.T  # the keypoint's offset from the object's origin, world axes
        X = arm + t0 + x[3:]
        h = np.einsum("nij,nj->ni", Pv[:, :, :3], X) + Pv[:, :, 3]
        return arm, h, X, R

    def residuals(x: np.ndarray) -> np.ndarray:
        _, h, _, _ = parts(x)
        return (sw * (h[:, :2] / h[:, 2:3] - target)).ravel()

    def jacobian(x: np.ndarray) -> np.ndarray:
        arm, h, _, _ = parts(x)
        z = h[:, 2:3]
        M = Pv[:, :, :3]
        dpix_dX = (M[:, :2, :] - (h[:, :2] / z)[:, :, None] * M[:, 2:3, :]) / z[:, :, None]  # (n,2,3)
        # a small rotation d (applied first) moves a keypoint by d x arm = -[arm]x d
        J = np.concatenate([-dpix_dX @ _skew(arm), dpix_dX], axis=2) * sw[:, :, None]
        return J.reshape(-1, 6)

    sol = least_squares(residuals, np.zeros(6), jac=jacobian, method="trf", loss="cauchy", f_scale=scale_px,
                        max_nfev=max_nfev, x_scale="jac", ftol=1e-6, xtol=1e-8)
    return rodrigues(sol.x[:3]) @ R0, t0 + sol.x[3:]


def score(P: np.ndarray, model: np.ndarray, uv: np.ndarray, w: np.ndarray, R: np.ndarray, t: np.ndarray,
          gate_px: float = GATE_PX) -> float:
    """Truncated quadratic cost of a pose (lower is better): detections beyond the gate cost the gate."""
    err = reprojection(P, model, R, t, uv)
    return float((w * np.minimum(err, gate_px) ** 2).sum())


def hypotheses(model: np.ndarray, points: np.ndarray, mask: np.ndarray, max_triples: int = 10
               ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Start poses from triangulated keypoints (k,3) where ``mask``: Kabsch on all of them and on
    triples of them (a wrong triangulated keypoint spoils only the triples holding it)."""
    idx = np.flatnonzero(mask)
    out = []
    if len(idx) >= 3:
        out.append(kabsch(model[idx], points[idx]))
    if len(idx) >= 4:
        for trio in itertools.islice(itertools.combinations(idx, 3), max_triples):
            trio = list(trio)
            if np.linalg.matrix_rank(model[trio] - model[trio].mean(0), tol=1e-3) >= 2:  # not collinear
                out.append(kabsch(model[trio], points[trio]))
    return out


def fit_pose(P: np.ndarray, model: np.ndarray, uv: np.ndarray, w: np.ndarray,
             starts: list[tuple[np.ndarray, np.ndarray]], gate_px: float = GATE_PX) -> PoseFit | None:
    """The best of ``starts`` by ``score``, refined, then refined again on its inliers alone."""
    if not starts or (w > 0).sum() < MIN_DETECTIONS or ((w > 0).any(axis=1)).sum() < MIN_VIEWS:
        return None
    R, t = min(starts, key=lambda s: score(P, model, uv, w, *s, gate_px))
    R, t = refine(P, model, uv, w, R, t)
    inl = (reprojection(P, model, R, t, uv) <= gate_px) & (w > 0)
    if inl.sum() < 3:
        return None
    R, t = refine(P, model, uv, w * inl, R, t)
    err = reprojection(P, model, R, t, uv)
    inl = (err <= gate_px) & (w > 0)
    if inl.sum() < 3:
        return None
    return PoseFit(R, t, inl, float(np.sqrt(np.mean(err[inl] ** 2))))


@dataclass
class RigidTracker:
    """One object's pose over frame sets: per-frame fits, pooled over a window while it rests."""

    model: np.ndarray  # (k,3) keypoints in the object's frame
    window: int = 20
    still_inliers: float = 0.8  # the window's pose must explain this share of what the frame's own does
    still_m: float = 0.02  # ... and its keypoints lie within this of the frame's own fit (mean)
    _frames: list = field(default_factory=list)
    _pose: tuple[np.ndarray, np.ndarray] | None = None
    restarts: int = 0

    def reset(self) -> None:
        self._frames, self._pose = [], None

    def update(self, P: np.ndarray, uv: np.ndarray, w: np.ndarray, points: np.ndarray, mask: np.ndarray
               ) -> PoseFit | None:
        """P (C,3,4), uv (C,k,2), w (C,k) this frame set's detections of the object; points (k,3)
        triangulated, mask (k,). Returns the pose reported now, or None (no pose this frame set)."""
        starts = hypotheses(self.model, points, np.asarray(mask, bool))
        if self._pose is not None:
            starts.append(self._pose)
        frame = fit_pose(P, self.model, uv, w, starts)
        if frame is None:
            if self._pose is not None and self._frames:
                return None  # nothing seen now: no report, the window waits
            self.reset()
            return None
        if self._pose is not None and self._still(P, uv, w, frame):
            self._frames.append((P, uv, w))
            del self._frames[:-self.window]
            Ps = np.concatenate([f[0] for f in self._frames])
            uvs = np.concatenate([f[1] for f in self._frames])
            ws = np.concatenate([f[2] for f in self._frames])
            pooled = fit_pose(Ps, self.model, uvs, ws, [self._pose, (frame.R, frame.t)])
            if pooled is not None:
                self._pose = (pooled.R, pooled.t)
                inl = pooled.inliers[-len(P):]
                return PoseFit(pooled.R, pooled.t, inl, pooled.rms_px)
        if self._pose is not None:
            self.restarts += 1
        self._frames = [(P, uv, w)]
        self._pose = (frame.R, frame.t)
        return frame

    def _still(self, P: np.ndarray, uv: np.ndarray, w: np.ndarray, frame: PoseFit) -> bool:
        R, t = self._pose
        held = ((reprojection(P, self.model, R, t, uv) <= GATE_PX) & (w > 0)).sum()
        moved = np.linalg.norm(frame.points(self.model) - (self.model @ R.T + t), axis=1).mean()
        return held >= self.still_inliers * frame.inliers.sum() and moved <= self.still_m
