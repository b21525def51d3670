"""Table 7.1's distance: symmetric closest-point distance per keypoint, averaged over time (pure).

For each keypoint and time step of one trajectory, the closest position of the same keypoint in
the other trajectory; distances averaged over the trajectory, then both directions averaged.
With masks, only keypoints observed in the validation trajectory count.
"""

from __future__ import annotations

import numpy as np


def closest_point_distance(a: np.ndarray, b: np.ndarray, mask_b: np.ndarray | None = None) -> float:
    """a: (Ta,N,3) prediction, b: (Tb,N,3) reference, mask_b: (Tb,N) observed flags of the reference."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    mask = np.ones(b.shape[:2], bool) if mask_b is None else np.asarray(mask_b, bool)
    per_point = []
    for i in range(a.shape[1]):
        bi = b[mask[:, i], i]
        if len(bi) == 0:
            continue
        d = np.linalg.norm(a[:, None, i] - bi[None], axis=-1)  # (Ta, Tb_observed)
        per_point.append(0.5 * (d.min(axis=1).mean() + d.min(axis=0).mean()))
    return float(np.mean(per_point)) if per_point else float("nan")


def trajectory_scores(pred_hands, pred_objects, demo) -> dict[str, float]:
    hands_ref = demo.hands.reshape(demo.steps, -1, 3)
    ph = np.asarray(pred_hands).reshape(len(pred_hands), -1, 3)
    return {
        "hand": closest_point_distance(ph, hands_ref),
        "object": closest_point_distance(pred_objects, demo.objects),
        "hand_masked": closest_point_distance(ph, hands_ref, demo.hand_mask.reshape(demo.steps, -1)),
        "object_masked": closest_point_distance(pred_objects, demo.objects, demo.object_mask),
    }
