"""Rigid objects posed from their keypoints (pure).

An object's model is its keypoints in its own frame, as the task defines them (the task's object
table, services/world/teacher.py, is the task definition; recon reads only the names and the
local points, never a pose). With three or more of its keypoints triangulated, a weighted Kabsch
fit poses the object and every model keypoint is reported, unseen ones included; a keypoint that
disagrees with the others by more than ``gate_m`` (or three times the fit's median residual, when
that is larger) is dropped and the fit repeated. With fewer,
the triangulated points are reported as they are, masked where missing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.recon.hand_model import kabsch
from services.world.teacher import OBJECT_POINTS, TASKS

LOO_GAIN = 3.0  # leaving one keypoint out divides the fit's RMS by this much: it was an outlier


@dataclass(frozen=True)
class ObjectModel:
    name: str
    points: np.ndarray  # (k,3) in the object's frame
    slice: slice  # its rows in the task's stacked object keypoints


def _fit_errors(model: np.ndarray, obs: np.ndarray, w: np.ndarray, use: np.ndarray) -> np.ndarray:
    R, t = kabsch(model[use], obs[use], w[use])
    return np.linalg.norm(model @ R.T + t - obs, axis=1)


def _fit_rms(model: np.ndarray, obs: np.ndarray, w: np.ndarray, use: np.ndarray) -> float:
    return float(np.sqrt(np.mean(_fit_errors(model, obs, w, use)[use] ** 2)))


def task_keypoint_names(task: str) -> list[str]:
    """The task's object keypoint names, ``object/point``, in the order the scene carries them."""
    if task not in OBJECT_POINTS:
        raise ValueError(f"unknown task {task!r} (known: {', '.join(TASKS)})")
    return [f"{obj}/{pt}" for obj, pts in OBJECT_POINTS[task].items() for pt in pts]


def object_models(task: str) -> list[ObjectModel]:
    if task not in OBJECT_POINTS:
        raise ValueError(f"unknown task {task!r} (known: {', '.join(TASKS)})")
    models, start = [], 0
    for obj, pts in OBJECT_POINTS[task].items():
        local = np.array(list(pts.values()), float)
        models.append(ObjectModel(obj, local, slice(start, start + len(local))))
        start += len(local)
    return models


def pose_objects(models: list[ObjectModel], points: np.ndarray, mask: np.ndarray,
                 weight: np.ndarray | None = None, gate_m: float = 0.006,
                 min_points: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """points (K,3) triangulated, mask (K,), weight (K,) optional. Returns keypoints (K,3), mask
    (K,) uint8, per object whether a rigid fit produced them (bool) and the fit's RMS residual (m,
    NaN where none), and which keypoints the fits used (K,) bool."""
    out = np.where(np.asarray(mask, bool)[:, None], np.nan_to_num(points), 0.0)
    out_mask = np.asarray(mask, np.uint8).copy()
    w_all = np.ones(len(points)) if weight is None else np.asarray(weight, float)
    posed = np.zeros(len(models), bool)
    rms = np.full(len(models), np.nan)
    used = np.zeros(len(points), bool)
    for i, m in enumerate(models):
        use = out_mask[m.slice].astype(bool)
        obs, w = out[m.slice], w_all[m.slice]
        while use.sum() >= min_points:
            err = _fit_errors(m.points, obs, w, use)
            fit_rms = float(np.sqrt(np.mean(err[use] ** 2)))
            # the gate scales with the fit's own typical residual: noisier cameras, wider gate
            bad = use & (err > max(gate_m, 3.0 * float(np.median(err[use]))))
            drop = None
            if use.sum() > min_points:
                # a keypoint whose removal shrinks the residual several-fold is not the object's
                loo = {k: _fit_rms(m.points, obs, w, use & (np.arange(len(use)) != k)) for k in np.flatnonzero(use)}
                k_best = min(loo, key=loo.get)
                if bad.any() or loo[k_best] < fit_rms / LOO_GAIN:
                    drop = k_best
            elif bad.any():
                break  # three keypoints that disagree: no pose
            if drop is None:
                R, t = kabsch(m.points[use], obs[use], w[use])
                out[m.slice] = m.points @ R.T + t
                out_mask[m.slice] = 1
                posed[i] = True
                rms[i] = fit_rms
                used[m.slice] = use
                break
            use[drop] = False
    return out, out_mask, posed, rms, used


@dataclass
class ObjectSmoother:
    """A short sliding window over each rigid fit: while an object stays put (every keypoint the fit
    used within ``still_m``, or three times the fit's RMS residual when the cameras are noisier, of
    the window's mean; keypoints the fit only extrapolated are too uncertain to judge by) the
    window's mean is reported, which averages the
    triangulation noise of a resting object; a move larger than that restarts the window at once,
    so a carried object is never dragged behind."""

    window: int = 8
    still_m: float = 0.008

    def __post_init__(self) -> None:
        self._hist: dict[str, list[np.ndarray]] = {}

    def update(self, models: list[ObjectModel], points: np.ndarray, posed: np.ndarray,
               rms: np.ndarray, used: np.ndarray) -> np.ndarray:
        out = points.copy()
        for m, ok, r in zip(models, posed, rms, strict=True):
            if not ok:
                self._hist.pop(m.name, None)
                continue
            new = points[m.slice]
            hist = self._hist.setdefault(m.name, [])
            gate = max(self.still_m, 3.0 * float(r))
            moved = np.linalg.norm(new - np.mean(hist, axis=0), axis=1)[used[m.slice]] if hist else []
            if len(moved) and moved.max() > gate:
                hist.clear()
            hist.append(new)
            del hist[:-self.window]
            out[m.slice] = np.mean(hist, axis=0)
        return out
