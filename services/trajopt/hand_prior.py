"""Hand-pose prior for the regulariser of thesis 7.22 (pure).

The thesis takes joint means and deviations from a hand pose dataset; we take them from the
teacher's demonstrations: the flexion angle at each finger joint (angle between consecutive bones
of the 21-keypoint hand) over all demonstration frames, mapped to the hand-arm model's joints
(`<finger>_j1` MCP, `_j2` PIP, `_j3` DIP; the model's thumb uses the human thumb's MCP/IP).
"""

from __future__ import annotations

import numpy as np

from shared.demo import Demo

# human keypoint chains (base, joint, next) per robot joint
CHAINS = {
    "thumb": [(1, 2, 3), (2, 3, 4), (2, 3, 4)],
    "index": [(0, 5, 6), (5, 6, 7), (6, 7, 8)],
    "middle": [(0, 9, 10), (9, 10, 11), (10, 11, 12)],
    "ring": [(0, 13, 14), (13, 14, 15), (14, 15, 16)],
}
MIN_STD = 0.05  # rad: a joint the teacher never moved still gets a finite deviation


def has_hand(model) -> bool:
    """Whether a RobotModel has the finger joints this prior is about (the hand-arm does, the gantry not)."""
    names = set(model.joint_names)
    return any(f"{finger}_j{k}" in names for finger in CHAINS for k in (1, 2, 3))


def flexion(hands: np.ndarray, a: int, b: int, c: int) -> np.ndarray:
    """Angle between bone a->b and bone b->c (0 = straight), for keypoints (..., 21, 3)."""
    u = hands[..., b, :] - hands[..., a, :]
    v = hands[..., c, :] - hands[..., b, :]
    cos = np.sum(u * v, axis=-1) / np.maximum(np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1), 1e-9)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def hand_pose_prior(demos: list[Demo], hand: int = 1) -> tuple[dict[str, float], dict[str, float]]:
    """Mean and standard deviation per hand-arm finger joint from the demonstrations' hand ``hand``."""
    hands = np.concatenate([d.hands[:, hand] for d in demos])
    mean, std = {}, {}
    for finger, chains in CHAINS.items():
        for k, (a, b, c) in enumerate(chains, start=1):
            angles = flexion(hands, a, b, c)
            mean[f"{finger}_j{k}"] = float(angles.mean())
            std[f"{finger}_j{k}"] = float(max(angles.std(), MIN_STD))
    return mean, std


def teacher_prior(task: str = "assembly", demos: int = 2, hand: int = 1) -> tuple[dict[str, float], dict[str, float]]:
    """hand_pose_prior of the SIMULATED scripted teacher's demonstrations (seeds 1..demos), what the
    trajopt service uses for the hand-arm when no recorded demonstrations are given."""
    from services.world.teacher import generate_demo  # the script is pure: no simulator needed

    return hand_pose_prior([generate_demo(task, seed) for seed in range(1, demos + 1)], hand)
