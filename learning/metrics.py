"""Table 7.1's distance (thesis 7.6.8), pure numpy.

For each keypoint and time step of one trajectory, the closest position of the same keypoint
anywhere in the other trajectory; those distances are averaged over the trajectory, both
directions are averaged (symmetric), then keypoints are averaged. Time shifts are forgiven,
detours are not. Masked variant ("observed masks" of Table 7.1): a keypoint sample counts only
where the validation (reference) trajectory observed it, on both sides: the reference's samples by
their flags, the prediction's by the reference's flag at the same time step (the rollout starts
where the reference starts and runs as long). A prediction sample during an occlusion of the
reference says nothing about where that point was seen, so it is not compared to the seen samples
(comparing it would score a method that keeps an object still while it is occluded above one that
carries it).
"""

from __future__ import annotations

import numpy as np


def closest_point_distance(a: np.ndarray, b: np.ndarray, mask_b: np.ndarray | None = None,
                           mask_a: np.ndarray | None = None) -> float:
    """a: (Ta,N,3) prediction, b: (Tb,N,3) reference, mask_b: (Tb,N) observed flags of b, mask_a:
    (Ta,N) flags of the samples of a that count (default: all).

    Keypoints never observed in b, or with no counted sample in a, are left out; NaN if none is left."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    if a.ndim != 3 or b.ndim != 3 or a.shape[1:] != b.shape[1:]:
        raise ValueError(f"trajectories must be (T,N,3) with equal N: got {a.shape} and {b.shape}")
    mask = np.ones(b.shape[:2], bool) if mask_b is None else np.asarray(mask_b, bool)
    if mask.shape != b.shape[:2]:
        raise ValueError(f"mask_b has shape {mask.shape}, expected {b.shape[:2]}")
    use_a = np.ones(a.shape[:2], bool) if mask_a is None else np.asarray(mask_a, bool)
    if use_a.shape != a.shape[:2]:
        raise ValueError(f"mask_a has shape {use_a.shape}, expected {a.shape[:2]}")
    # (N, Ta, Tb) pairwise distances per keypoint; unobserved reference samples become +inf
    seen = mask.any(axis=0) & use_a.any(axis=0)
    if not seen.any():
        return float("nan")
    pa, pb = a.transpose(1, 0, 2)[seen], b.transpose(1, 0, 2)[seen]
    # squared distances through one batched product (much faster than differencing (N,Ta,Tb,3))
    d2 = (pa ** 2).sum(-1)[:, :, None] + (pb ** 2).sum(-1)[:, None, :] - 2.0 * pa @ pb.transpose(0, 2, 1)
    m, ua = mask.T[seen], use_a.T[seen]  # (N', Tb), (N', Ta)
    d2 = np.where(m[:, None, :] & ua[:, :, None], np.maximum(d2, 0.0), np.inf)
    a_min = np.sqrt(d2.min(axis=2))  # (N', Ta): every counted predicted sample to the nearest observed reference
    a_to_b = np.where(ua, a_min, 0.0).sum(axis=1) / ua.sum(axis=1)
    b_min = np.sqrt(d2.min(axis=1))  # (N', Tb): every reference sample to the nearest counted prediction
    b_to_a = np.where(m, b_min, 0.0).sum(axis=1) / m.sum(axis=1)
    return float(np.mean(0.5 * (a_to_b + b_to_a)))


SCORE_KEYS = ("hand", "object", "hand_masked", "object_masked")


def aligned(mask: np.ndarray, steps: int) -> np.ndarray:
    """The reference's (T,N) flags for a prediction of ``steps`` samples on the same clock: cut, or
    held at their last value past the reference's end (the scene stays as it ended)."""
    idx = np.minimum(np.arange(steps), len(mask) - 1)
    return mask[idx]


def trajectory_scores(pred_hands: np.ndarray, pred_objects: np.ndarray, demo,
                      keys: tuple[str, ...] = SCORE_KEYS) -> dict[str, float]:
    """The columns of Table 7.1 (all four, or ``keys``) for one rollout against one validation
    Demo (metres). Each column costs a pairwise distance pass: training selection asks for two."""
    t = demo.steps
    hands_ref = np.asarray(demo.hands).reshape(t, -1, 3)
    ph = np.asarray(pred_hands).reshape(len(pred_hands), -1, 3)
    po = np.asarray(pred_objects).reshape(len(pred_objects), -1, 3)
    hand_mask = np.asarray(demo.hand_mask, bool).reshape(t, -1)
    object_mask = np.asarray(demo.object_mask, bool)
    pairs = {"hand": (ph, hands_ref, None, None), "object": (po, demo.objects, None, None),
             "hand_masked": (ph, hands_ref, hand_mask, aligned(hand_mask, len(ph))),
             "object_masked": (po, demo.objects, object_mask, aligned(object_mask, len(po)))}
    return {k: closest_point_distance(*pairs[k]) for k in keys}
