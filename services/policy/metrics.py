"""Table 7.1's distance (thesis 7.6.8), pure numpy.

For each keypoint and time step of one trajectory, the closest position of the same keypoint
anywhere in the other trajectory; those distances are averaged over the trajectory, both
directions are averaged (symmetric), then keypoints are averaged. Time shifts are forgiven,
detours are not. Masked variant: only keypoints observed in the validation (reference)
trajectory count, in both directions.
"""

from __future__ import annotations

import numpy as np


def closest_point_distance(a: np.ndarray, b: np.ndarray, mask_b: np.ndarray | None = None) -> float:
    """a: (Ta,N,3) prediction, b: (Tb,N,3) reference, mask_b: (Tb,N) observed flags of b.

    Keypoints never observed in b are left out; NaN if none is left."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    if a.ndim != 3 or b.ndim != 3 or a.shape[1:] != b.shape[1:]:
        raise ValueError(f"trajectories must be (T,N,3) with equal N: got {a.shape} and {b.shape}")
    mask = np.ones(b.shape[:2], bool) if mask_b is None else np.asarray(mask_b, bool)
    if mask.shape != b.shape[:2]:
        raise ValueError(f"mask_b has shape {mask.shape}, expected {b.shape[:2]}")
    # (N, Ta, Tb) pairwise distances per keypoint; unobserved reference samples become +inf
    seen = mask.any(axis=0)
    if not seen.any():
        return float("nan")
    pa, pb = a.transpose(1, 0, 2)[seen], b.transpose(1, 0, 2)[seen]
    # squared distances through one batched product (much faster than differencing (N,Ta,Tb,3))
    d2 = (pa ** 2).sum(-1)[:, :, None] + (pb ** 2).sum(-1)[:, None, :] - 2.0 * pa @ pb.transpose(0, 2, 1)
    d2 = np.where(mask.T[seen][:, None, :], np.maximum(d2, 0.0), np.inf)
    a_to_b = np.sqrt(d2.min(axis=2)).mean(axis=1)  # every predicted sample to the nearest observed reference
    b_min = np.sqrt(d2.min(axis=1))  # (N', Tb): every reference sample to the nearest prediction
    m = mask.T[seen]
    b_to_a = np.where(m, b_min, 0.0).sum(axis=1) / m.sum(axis=1)
    return float(np.mean(0.5 * (a_to_b + b_to_a)))


SCORE_KEYS = ("hand", "object", "hand_masked", "object_masked")


def trajectory_scores(pred_hands: np.ndarray, pred_objects: np.ndarray, demo,
                      keys: tuple[str, ...] = SCORE_KEYS) -> dict[str, float]:
    """The columns of Table 7.1 (all four, or ``keys``) for one rollout against one validation
    Demo (metres). Each column costs a pairwise distance pass: training selection asks for two."""
    t = demo.steps
    hands_ref = np.asarray(demo.hands).reshape(t, -1, 3)
    ph = np.asarray(pred_hands).reshape(len(pred_hands), -1, 3)
    po = np.asarray(pred_objects).reshape(len(pred_objects), -1, 3)
    pairs = {"hand": (ph, hands_ref, None), "object": (po, demo.objects, None),
             "hand_masked": (ph, hands_ref, np.asarray(demo.hand_mask).reshape(t, -1)),
             "object_masked": (po, demo.objects, demo.object_mask)}
    return {k: closest_point_distance(*pairs[k]) for k in keys}
