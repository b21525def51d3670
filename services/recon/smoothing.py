"""Offline smoothing of reconstructed keypoint tracks over a whole recording (thesis 5.3's
Cartesian jerk regulariser, applied to the reconstructed points), pure.

Each keypoint's track is the minimiser of

    sum_t m_t * rho((x_t - y_t) / noise) + sum_t ((x_{t+3} - 3 x_{t+2} + 3 x_{t+1} - x_t) / (jerk * dt^3))^2

where y_t is the reconstructed point, m_t its mask, ``noise`` (m) the reconstruction's error
per sample, ``jerk`` (m/s^3) the third derivative a real motion keeps, and rho a Huber loss
(solved by reweighted least squares: a point on the wrong hand or finger counts linearly). The
weights are physical, so one setting serves any frame rate: at 5 frame sets a second dt^3 is
large and the prior barely acts; at 50 Hz it removes the frame-to-frame jitter each
independently reconstructed frame set carries.

Gaps (masked samples) up to ``max_gap_s`` are filled by the prior (the smoothest curve through
the neighbours) and reported; a longer gap splits the track, and its samples stay masked. Each
linear system is banded (bandwidth 3) and symmetric positive definite, solved in O(T).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import solveh_banded

# third difference: x[t+3] - 3 x[t+2] + 3 x[t+1] - x[t]
_D3 = np.array([-1.0, 3.0, -3.0, 1.0])


@dataclass(frozen=True)
class SmoothParams:
    noise_m: float  # reconstruction error of one sample (m)
    jerk_m_s3: float  # third derivative of the real motion the prior allows (m/s^3)
    max_gap_s: float = 0.2  # longer gaps split a track and stay masked
    huber: float = 2.0  # residuals beyond this many ``noise_m`` count linearly
    iterations: int = 4  # reweighted least-squares passes


def _jerk_band(n: int) -> np.ndarray:
    """D3^T D3 of an n-sample track in upper banded form (4, n) for ``solveh_banded``."""
    band = np.zeros((4, n))
    for i in range(4):  # third-difference row r touches samples r..r+3
        for j in range(i, 4):
            band[3 - (j - i), j:n - 3 + j] += _D3[i] * _D3[j]
    return band


def smooth_segment(y: np.ndarray, weight: np.ndarray, params: SmoothParams, dt: float) -> np.ndarray:
    """The smoothed track (n,D) of samples ``y`` (n,D) seen with ``weight`` (n,) in [0,1] (0:
    unseen, filled by the prior). Needs at least 3 seen samples (a quadratic has no jerk)."""
    base = np.asarray(weight, float)
    y = np.where(base[:, None] > 0, np.asarray(y, float), 0.0)  # unseen samples (NaN or not) say nothing
    n = len(y)
    if n < 4:
        return y
    prior = _jerk_band(n) * (params.noise_m / (params.jerk_m_s3 * dt ** 3)) ** 2
    w, x = base, y
    for _ in range(params.iterations):
        a = prior.copy()
        a[3] += w
        x = solveh_banded(a, w[:, None] * y, lower=False, check_finite=False)
        r = np.linalg.norm(x - y, axis=1) / params.noise_m
        w = base * np.where(r > params.huber, params.huber / np.maximum(r, 1e-12), 1.0)
    return x


def segments(seen: np.ndarray, max_gap: int) -> list[tuple[int, int]]:
    """[start, stop) spans from a seen sample to a seen sample with no gap longer than ``max_gap``."""
    idx = np.flatnonzero(seen)
    if not len(idx):
        return []
    out, start = [], idx[0]
    for a, b in zip(idx[:-1], idx[1:], strict=True):
        if b - a - 1 > max_gap:
            out.append((start, a + 1))
            start = b
    out.append((start, idx[-1] + 1))
    return out


def smooth_tracks(points: np.ndarray, mask: np.ndarray, dt: float, params: SmoothParams
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed keypoints (T,...,3) and their mask (T,...): every span of a track without a gap over
    ``params.max_gap_s`` is smoothed and its short gaps filled; samples outside a span (before the
    first sighting, in a long gap) keep their value and mask. Spans with fewer than 3 seen samples
    are left as they are."""
    if dt <= 0 or not np.isfinite(dt):
        raise ValueError(f"sample period {dt!r} s: must be a positive number")
    shape, t = np.shape(points), len(points)
    pts = np.asarray(points, float).reshape(t, -1, 3)
    seen = np.asarray(mask, bool).reshape(t, -1) & np.isfinite(pts).all(axis=-1)
    out, out_mask = pts.copy(), seen.copy()
    max_gap = int(round(params.max_gap_s / dt))
    for k in range(pts.shape[1]):
        for a, b in segments(seen[:, k], max_gap):
            if seen[a:b, k].sum() < 3:
                continue
            out[a:b, k] = smooth_segment(pts[a:b, k], seen[a:b, k].astype(float), params, dt)
            out_mask[a:b, k] = True
    return out.reshape(shape), out_mask.reshape(shape[:-1])


# Settings for the simulated rig's reconstruction at 50 Hz, chosen on the assembly protocol's seed-1
# training demonstrations (docs/perception.md, "Smoothing"): hands move, objects mostly rest or
# ride in a hand; a filled object gap longer than 0.2 s was 9 mm off.
HANDS = SmoothParams(noise_m=0.004, jerk_m_s3=30.0)
OBJECTS = SmoothParams(noise_m=0.004, jerk_m_s3=3.0)
