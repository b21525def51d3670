"""The flat keypoint state of demonstrations, shared by the naive replay (naive.py, which the node
can serve) and the baselines of evaluation/baselines (pure numpy).

The baselines work on the thesis's low-level representation: observations are the 3-D keypoints
of both hands and all objects flattened into one vector (hands first), actions are their
velocities. Occluded samples are filled by linear interpolation over time before fitting
(thesis 7.6.8, [55]).
"""

from __future__ import annotations

import numpy as np

from shared.demo import KEYPOINTS_PER_HAND, Demo

HAND_DIMS = 2 * KEYPOINTS_PER_HAND * 3


class BaselineError(RuntimeError):
    """A baseline was used out of order (rollout before fit) or given unusable data."""


def raw_state(demo: Demo) -> np.ndarray:
    """(T, D) hands then objects, as recorded (occluded samples untouched)."""
    t = demo.steps
    return np.concatenate([demo.hands.reshape(t, -1), demo.objects.reshape(t, -1)], axis=1).astype(float)


def state_mask(demo: Demo) -> np.ndarray:
    """(T, D) bool: observed flag of every coordinate of the flat state."""
    t = demo.steps
    return np.concatenate([np.repeat(demo.hand_mask.reshape(t, -1), 3, axis=1),
                           np.repeat(demo.object_mask.reshape(t, -1), 3, axis=1)], axis=1).astype(bool)


def interpolate_occluded(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Linear interpolation over time of unobserved entries (constant beyond the first/last
    observation). Columns never observed keep their finite values, NaN becomes 0."""
    out = np.array(x, float, copy=True)
    mask = np.asarray(mask, bool) & np.isfinite(out)
    t = np.arange(len(out))
    for j in np.flatnonzero(~mask.all(axis=0)):
        seen = mask[:, j]
        if seen.any():
            out[:, j] = np.interp(t, t[seen], out[seen, j])
    return np.nan_to_num(out, nan=0.0)


def flat_state(demo: Demo) -> np.ndarray:
    """(T, D) float64 flat state with occluded samples interpolated."""
    return interpolate_occluded(raw_state(demo), state_mask(demo))


def split_state(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(S, D) flat states -> hands (S,2,21,3), objects (S,K,3)."""
    x = np.asarray(x, float)
    return x[:, :HAND_DIMS].reshape(len(x), 2, KEYPOINTS_PER_HAND, 3), x[:, HAND_DIMS:].reshape(len(x), -1, 3)


def hold_to(x: np.ndarray, steps: int) -> np.ndarray:
    """First ``steps`` rows of x; past its end the last row is held (the motion has finished)."""
    idx = np.minimum(np.arange(steps), len(x) - 1)
    return x[idx]


def check_train(train: list[Demo], minimum: int = 1) -> None:
    if len(train) < minimum:
        raise BaselineError(f"need at least {minimum} training demonstration(s), got {len(train)}")
    ks = {d.objects.shape[1] for d in train}
    if len(ks) != 1:
        raise BaselineError(f"training demonstrations disagree on the number of object keypoints: {sorted(ks)}")
