"""Per-frame fit of the articulated hand model to triangulated keypoints, with a short sliding
window (pure).

A ``HandTracker`` per hand: an initialisation phase collects the first confident frames (every
keypoint triangulated) and estimates the person's shape from them (services/recon/hand_model.py);
then every frame is fitted: Kabsch aligns the palm template to the observed palm points (the
wrist pose) when the track is new, otherwise the window extrapolates the last poses (temporal warm
start); Levenberg-Marquardt (scipy's trust-region variant, which honours the joint limits as
bounds) then solves wrist pose and joint angles together. A hand that is not seen for a few frames
drops its window, so when it returns the fit starts again from Kabsch.

What a fitted hand reports is the model fused with the observation: a keypoint that was
triangulated is the mean of the model's and the triangulated position (``FitConfig.blend``), one
that was not is the model's. The model's own error (a shape estimated from a few frames, a hand
it does not quite describe) and the triangulation's (2-D peaks) are of the same size and largely
independent, so their mean beats either (docs/perception.md).
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from services.recon.hand_model import (
    FRAME_POINTS,
    N_JOINTS,
    N_PARAMS,
    PALM,
    HandShape,
    estimate_shape,
    forward,
    forward_jacobian,
    joint_bounds,
    kabsch,
    mirror,
    rodrigues,
    rotvec,
)

LIMIT_STIFFNESS = 1.0  # metres of residual per radian beyond a joint limit: a hard wall for LM
REST_JOINTS = np.concatenate([np.tile([0.0, 0.3, 0.3, 0.2], 5), np.zeros(3)])  # relaxed: the Kabsch start
STRETCH_PRIOR = 0.02  # metres of residual per unit of thumb stretch (10 % costs as much as 2 mm)


def fuse(model: np.ndarray, triangulated: np.ndarray, seen: np.ndarray, blend: float) -> np.ndarray:
    """Model keypoints (...,3) moved ``blend`` of the way to the triangulated ones where ``seen``
    (...): what a fitted hand reports, live and offline."""
    return np.where(np.asarray(seen, bool)[..., None], model + blend * (triangulated - model), model)


@dataclass
class FitConfig:
    init_frames: int = 8  # confident frames that estimate the person's shape
    init_missing: int = 2  # keypoints a confident frame may lack
    override: float = 2.5  # an observed keypoint this many fit RMS from the model stays as observed
    window: int = 4  # poses kept for the warm start
    lost_after: int = 3  # frames unseen before the window is dropped
    min_points: int = 6  # observed keypoints a fit needs
    max_rms_m: float = 0.012  # a fit worse than this is refused (the triangulated points are kept)
    prior: float = 0.004  # metres of residual per radian away from the warm start (keeps unseen joints put)
    max_nfev: int = 30
    blend: float = 0.5  # a fitted keypoint's share of its triangulated position (0: the model alone)


@dataclass
class HandTracker:
    side: str  # "left" or "right": a left hand is the mirror image
    config: FitConfig = field(default_factory=FitConfig)
    shape: HandShape | None = None
    _init: list = field(default_factory=list)
    _window: collections.deque = field(default_factory=collections.deque)
    _missed: int = 0
    resets: int = 0
    last_rms: float = float("nan")
    nfev: int = 0
    overridden: int = 0
    last_params: np.ndarray | None = None  # this frame's fit (what the offline refinement starts from)

    def __post_init__(self) -> None:
        self._lo, self._hi = joint_bounds()

    @property
    def tracking(self) -> bool:
        return bool(self._window)

    def update(self, points: np.ndarray, mask: np.ndarray, weight: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, bool]:
        """points (21,3) triangulated, mask (21,) of those that exist, weight (21,) optional (views
        that agreed). Returns keypoints (21,3), their mask (21,) and whether the model produced them
        (then every keypoint is filled in, occluded ones included)."""
        self.last_params = None
        mask = np.asarray(mask, bool)
        points = np.where(mask[:, None], np.nan_to_num(points), 0.0)
        if mask.sum() < self.config.min_points:
            self._lose()
            return points, mask.astype(np.uint8), False
        self._missed = 0
        if self.shape is None:
            if mask[FRAME_POINTS].all() and mask.sum() >= 21 - self.config.init_missing:
                self._init.append(np.where(mask[:, None], points, np.nan))
                if len(self._init) >= self.config.init_frames:
                    self.shape = estimate_shape(self._init, self.side)
                    self._init = []
            return points, mask.astype(np.uint8), False
        w = np.ones(21) if weight is None else np.asarray(weight, float)
        params = self._fit(points, mask, w)
        if params is None:
            return points, mask.astype(np.uint8), False
        self._window.append(params)
        self.last_params = params
        while len(self._window) > self.config.window:
            self._window.popleft()
        model = forward(self.shape, params, self.side)
        # The model is a prior, not a cage: an observed keypoint much further from it than the fit's
        # typical residual is kept as observed (a hand the model does not quite describe).
        resid = np.linalg.norm(model - points, axis=1)
        keep = mask & (w >= 3) & (resid > self.config.override * self.last_rms)
        self.overridden = int(keep.sum())
        fused = fuse(model, points, mask, self.config.blend)
        return np.where(keep[:, None], points, fused), np.ones(21, np.uint8), True

    def finish_initialisation(self, min_frames: int) -> bool:
        """Estimate the shape now from the confident frames collected so far (an offline pass
        that collects every one of them: ``init_frames`` above the recording's length), when there
        are at least ``min_frames``. Returns whether the tracker has a shape."""
        if self.shape is None and len(self._init) >= min_frames:
            self.shape = estimate_shape(self._init, self.side)
            self._init = []
        return self.shape is not None

    def _lose(self) -> None:
        self._missed += 1
        if self._missed >= self.config.lost_after and self._window:
            self._window.clear()
            self.resets += 1

    def _kabsch_start(self, points: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
        seen = mask[PALM]
        if seen.sum() < 3:
            return None
        template = self.shape.palm @ mirror(self.side)
        R, t = kabsch(template[seen], points[PALM][seen])
        return np.concatenate([rotvec(R), t, REST_JOINTS])

    def _warm_start(self) -> np.ndarray | None:
        if not self._window:
            return None
        last = self._window[-1]
        if len(self._window) < 2:
            return last.copy()
        guess = last.copy()
        guess[3:6] += 0.5 * (last[3:6] - self._window[-2][3:6])  # the wrist: damped constant velocity
        return guess

    def _solve(self, start: np.ndarray, points: np.ndarray, mask: np.ndarray, w: np.ndarray
               ) -> tuple[np.ndarray, float]:
        idx = np.flatnonzero(mask)
        sw = np.sqrt(np.clip(w[idx], 0.0, None))[:, None]
        target = points[idx]
        prior_ref = start[6:].copy()
        prior_ref[N_JOINTS:] = 0.0  # the thumb's stretch is held toward the person's lengths
        lam = np.full(N_PARAMS - 6, self.config.prior)
        lam[N_JOINTS:] = STRETCH_PRIOR
        # The rotation is solved as a correction on the start's rotation: no wrap-around.
        R0 = rodrigues(start[:3])
        cache: dict = {}

        def model(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            key = x.tobytes()
            if key not in cache:
                cache.clear()
                cache[key] = forward_jacobian(self.shape, x, self.side, R0)
            return cache[key]

        lo, hi = self._lo[6:], self._hi[6:]

        def residuals(x: np.ndarray) -> np.ndarray:
            pts, q = model(x)[0], x[6:]
            limit = LIMIT_STIFFNESS * (np.maximum(q - hi, 0.0) - np.maximum(lo - q, 0.0))
            return np.concatenate([(sw * (pts[idx] - target)).ravel(), lam * (q - prior_ref), limit])

        def jacobian(x: np.ndarray) -> np.ndarray:
            J = model(x)[1][idx] * sw[:, :, None]
            q = x[6:]
            limit_rows = np.zeros((N_PARAMS - 6, N_PARAMS))
            limit_rows[:, 6:] = np.diag(LIMIT_STIFFNESS * ((q > hi) | (q < lo)))
            return np.concatenate([J.reshape(-1, N_PARAMS), prior_rows, limit_rows])

        prior_rows = np.zeros((N_PARAMS - 6, N_PARAMS))
        prior_rows[:, 6:] = np.diag(lam)

        def pack(x: np.ndarray) -> np.ndarray:
            p = x.copy()
            p[:3] = rotvec(rodrigues(x[:3]) @ R0)
            return p

        x0 = start.copy()
        x0[:3] = 0.0
        x0[6:] = np.clip(x0[6:], self._lo[6:] + 1e-6, self._hi[6:] - 1e-6)
        sol = least_squares(residuals, x0, jac=jacobian, method="lm", max_nfev=self.config.max_nfev,
                            x_scale="jac", ftol=1e-4, xtol=1e-6)
        self.nfev = sol.nfev
        p = pack(sol.x)
        p[6:] = np.clip(p[6:], lo, hi)  # the limit penalty leaves at most a sliver outside
        err = forward(self.shape, p, self.side)[idx] - target
        return p, float(np.sqrt((err ** 2).sum(axis=1).mean()))

    def _fit(self, points: np.ndarray, mask: np.ndarray, w: np.ndarray) -> np.ndarray | None:
        best: tuple[np.ndarray, float] | None = None
        for start in (self._warm_start(), self._kabsch_start(points, mask)):
            if start is None:
                continue
            params, rms = self._solve(start, points, mask, w)
            if best is None or rms < best[1]:
                best = (params, rms)
            if rms <= self.config.max_rms_m:
                break  # a warm start that fits needs no Kabsch restart
        if best is None:
            return None
        self.last_rms = best[1]
        return best[0] if best[1] <= self.config.max_rms_m else None
