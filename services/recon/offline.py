"""Offline refinement of a hand's whole trajectory (thesis 5.3, 5.6), pure.

Starting from the live per-frame fits, every frame's wrist pose, joint angles and thumb stretch
are solved together as one sparse robust least-squares problem
(``scipy.optimize.least_squares``, trust-region reflective with a sparse finite-difference
Jacobian):

- reprojection: each 2-D detection of a keypoint against the model keypoint projected into that
  camera, weighted by the detector's confidence, under a Huber loss (outliers count linearly);
- joint limits: a stiff penalty beyond each limit;
- smoothness: the third difference in time (jerk) of every keypoint's world position;
- the thumb's stretch held toward the person's lengths.

Frames without a live fit (occlusion, the hand briefly lost) start from the pose interpolated
between their neighbours (rotations by slerp) and are filled by the smoothness term and whatever
detections they have: gap filling. A gap the hand could only have crossed faster than a hand moves
(it left and came back elsewhere) splits the trajectory instead (``segments``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation, Slerp

from services.recon.hand_fit import FitConfig
from services.recon.hand_model import N_JOINTS, N_PARAMS, HandShape, forward, joint_bounds
from services.recon.triangulation import project

# Fastest a hand may move across a gap that is filled: where the wrist moves slowly the
# interpolated start is close to where the hand was; the simulated teacher's hands move at up to
# 0.7 m/s between frame sets, a demonstration's reset jumps at 2.3-2.9 m/s.
MAX_GAP_SPEED_M_S = 0.5


@dataclass
class OfflineConfig:
    huber_px: float = 3.0  # reprojection residuals beyond this count linearly
    jerk_px_per_m: float = 0.0  # weight of a keypoint's third time difference (px per metre): see docs/perception.md
    limit_px_per_rad: float = 100.0
    stretch_px: float = 5.0  # per unit of thumb stretch (10 % costs half a pixel)
    max_nfev: int = 30
    max_gap_speed_m_s: float = MAX_GAP_SPEED_M_S  # see segments()
    blend: float = FitConfig.blend  # a refined keypoint's share of its triangulated position, as live


def fill_gaps(params: np.ndarray, have: np.ndarray) -> np.ndarray:
    """(T,P) per-frame parameters with rows ``have`` known: the others interpolated between the
    nearest known frames (rotation vectors by slerp, the rest linearly), held at the ends."""
    known = np.flatnonzero(have)
    if len(known) == 0:
        raise ValueError("no frame has a fit to start from")
    out = params.copy()
    t = np.arange(len(params), dtype=float)
    for j in range(3, params.shape[1]):
        out[:, j] = np.interp(t, known, params[known, j])
    if len(known) == 1:
        out[:, :3] = params[known[0], :3]
    else:
        slerp = Slerp(known.astype(float), Rotation.from_rotvec(params[known, :3]))
        out[:, :3] = slerp(np.clip(t, known[0], known[-1])).as_rotvec()
    return out


def segments(wrist: np.ndarray, have: np.ndarray, stamps: np.ndarray,
             max_speed: float = MAX_GAP_SPEED_M_S) -> list[np.ndarray]:
    """The frames to refine as one trajectory each: from the first to the last live fit, split at
    every gap (frames without a fit) across which the wrist (T,3) would have to move faster than
    ``max_speed`` (m/s): a hand that left and came back elsewhere, or a demonstration reset, is
    not interpolated; the gap's frames are in no segment."""
    known = np.flatnonzero(have)
    if not len(known):
        return []
    out, start = [], known[0]
    for a, b in zip(known[:-1], known[1:], strict=True):
        if b - a > 1 and np.linalg.norm(wrist[b] - wrist[a]) > max_speed * (stamps[b] - stamps[a]):
            out.append(np.arange(start, a + 1))
            start = b
    out.append(np.arange(start, known[-1] + 1))
    return out


def _sparsity(frame_of_obs: np.ndarray, T: int) -> lil_matrix:
    n_obs, n_q, n_s = len(frame_of_obs), N_PARAMS - 6, N_PARAMS - 6 - N_JOINTS
    S = lil_matrix((2 * n_obs + max(T - 3, 0) * 63 + T * (n_q + n_s), T * N_PARAMS), dtype=np.uint8)
    for i, t in enumerate(frame_of_obs):
        S[2 * i:2 * i + 2, t * N_PARAMS:(t + 1) * N_PARAMS] = 1
    row = 2 * n_obs
    for t in range(max(T - 3, 0)):  # jerk couples four frames
        S[row:row + 63, t * N_PARAMS:(t + 4) * N_PARAMS] = 1
        row += 63
    for t in range(T):  # joint limits
        S[row + np.arange(n_q), t * N_PARAMS + 6 + np.arange(n_q)] = 1
        row += n_q
    for t in range(T):  # thumb stretch
        S[row + np.arange(n_s), t * N_PARAMS + 6 + N_JOINTS + np.arange(n_s)] = 1
        row += n_s
    return S


def refine_hand(shape: HandShape, side: str, P: np.ndarray, uv: np.ndarray, confidence: np.ndarray,
                init: np.ndarray, have: np.ndarray, config: OfflineConfig | None = None
                ) -> tuple[np.ndarray, dict]:
    """P (C,3,4); uv (T,C,21,2) detections; confidence (T,C,21) (0: none or rejected); init
    (T,N_PARAMS) live fits, valid where ``have`` (T,). Returns the refined (T,N_PARAMS) and a
    summary (median reprojection error before and after, gaps filled)."""
    cfg = config or OfflineConfig()
    T = uv.shape[0]
    x0 = fill_gaps(init, have)
    lo, hi = joint_bounds()
    lo_j, hi_j = lo[6:], hi[6:]
    w = np.sqrt(np.clip(np.nan_to_num(confidence), 0.0, None))  # (T,C,21)
    obs = w > 0
    uv = np.nan_to_num(uv)
    n_obs = int(obs.sum())

    def residuals(x: np.ndarray) -> np.ndarray:
        X = x.reshape(T, N_PARAMS)
        pts = np.stack([forward(shape, X[t], side) for t in range(T)])  # (T,21,3)
        pix, _ = project(P, pts)  # (C,T,21,2)
        rep = (w[..., None] * (pix.transpose(1, 0, 2, 3) - uv))[obs].ravel()
        jerk = (pts[3:] - 3 * pts[2:-1] + 3 * pts[1:-2] - pts[:-3]).ravel() * cfg.jerk_px_per_m
        q = X[:, 6:]
        limit = cfg.limit_px_per_rad * (np.maximum(q - hi_j, 0.0) - np.maximum(lo_j - q, 0.0))
        return np.concatenate([rep, jerk, limit.ravel(), cfg.stretch_px * q[:, N_JOINTS:].ravel()])

    def median_px(r: np.ndarray) -> float:
        if not n_obs:
            return float("nan")
        return float(np.median(np.linalg.norm(r[:2 * n_obs].reshape(-1, 2), axis=1) / w[obs]))

    before = residuals(x0.ravel())
    sol = least_squares(residuals, x0.ravel(), jac_sparsity=_sparsity(np.nonzero(obs)[0], T).tocsr(),
                        method="trf", loss="huber", f_scale=cfg.huber_px, max_nfev=cfg.max_nfev,
                        tr_solver="lsmr")  # no x_scale="jac": zero columns of a sparse FD Jacobian stall it
    out = sol.x.reshape(T, N_PARAMS)
    out[:, 6:] = np.clip(out[:, 6:], lo_j, hi_j)
    return out, {"frames": T, "gaps_filled": int((~np.asarray(have, bool)).sum()), "evaluations": int(sol.nfev),
                 "median_reprojection_px_before": round(median_px(before), 3),
                 "median_reprojection_px_after": round(median_px(sol.fun), 3)}
