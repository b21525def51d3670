"""Assemble a Scene observation from reconstructed points and glove data (pure)."""

from __future__ import annotations

from typing import Any

import numpy as np

from shared import msgs
from shared.demo import KEYPOINTS_PER_HAND, TACTILE_REGIONS


def split_points(points: np.ndarray, mask: np.ndarray, n_hands: int) -> tuple[np.ndarray, np.ndarray,
                                                                             np.ndarray, np.ndarray]:
    """The stacked point list is hands first (n_hands*21), then object points. Masked points are
    zero, never NaN."""
    nh = n_hands * KEYPOINTS_PER_HAND
    points = np.where(np.asarray(mask, bool)[:, None], np.nan_to_num(points), 0.0)
    hands = points[:nh].reshape(n_hands, KEYPOINTS_PER_HAND, 3)
    return hands, mask[:nh].reshape(n_hands, KEYPOINTS_PER_HAND), points[nh:], mask[nh:]


def tactile_matrix(hand_names: list[str], latest: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Per-hand region pressures (H,R) and mask from the newest region means per glove."""
    tactile = np.zeros((len(hand_names), len(TACTILE_REGIONS)), np.float32)
    mask = np.zeros_like(tactile, dtype=np.uint8)
    for i, hand in enumerate(hand_names):
        if hand in latest:
            tactile[i] = latest[hand]
            mask[i] = 1
    return tactile, mask


def scene_message(stamp: float, hand_names: list[str], hands: np.ndarray, hand_mask: np.ndarray,
                  object_names: list[str], objects: np.ndarray, object_mask: np.ndarray,
                  tactile: np.ndarray, tactile_mask: np.ndarray) -> Any:
    """The xm_msgs/msg/Scene of one frame set."""
    return msgs.make(
        "xm_msgs/msg/Scene", header=msgs.header(stamp, "world"), hand_names=list(hand_names),
        hand_keypoints=np.asarray(hands, np.float32).ravel(), hand_mask=np.asarray(hand_mask, np.uint8).ravel(),
        object_names=list(object_names), object_keypoints=np.asarray(objects, np.float32).ravel(),
        object_mask=np.asarray(object_mask, np.uint8).ravel(), tactile_regions=list(TACTILE_REGIONS),
        tactile=np.asarray(tactile, np.float32).ravel(), tactile_mask=np.asarray(tactile_mask, np.uint8).ravel())
