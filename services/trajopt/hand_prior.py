"""Hand-pose prior for the regulariser of thesis 7.22 (pure).

The thesis takes joint means and deviations from a hand pose dataset; we take them from the
teacher's demonstrations: the flexion angle at each finger joint (angle between consecutive bones
of the 21-keypoint hand) over all demonstration frames, mapped to the robot's finger joints by its
description's ``finger_flexion`` (shared/robots).
"""

from __future__ import annotations

import numpy as np

from services.world.teacher import generate_demo
from shared.demo import Demo
from shared.robots.registry import REGISTRY

MIN_STD = 0.05  # rad: a joint the teacher never moved still gets a finite deviation
# every described robot's finger joints (their names do not collide): the default of hand_pose_prior
ALL_FLEXION = {j: chain for d in REGISTRY.values() for j, chain in d.finger_flexion.items()}


def flexion(hands: np.ndarray, a: int, b: int, c: int) -> np.ndarray:
    """Angle between bone a->b and bone b->c (0 = straight), for keypoints (..., 21, 3)."""
    u = hands[..., b, :] - hands[..., a, :]
    v = hands[..., c, :] - hands[..., b, :]
    cos = np.sum(u * v, axis=-1) / np.maximum(np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1), 1e-9)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def hand_pose_prior(demos: list[Demo], hand: int = 1, chains: dict[str, tuple[int, int, int]] | None = None
                    ) -> tuple[dict[str, float], dict[str, float]]:
    """Mean and standard deviation per robot finger joint (``chains``: joint -> human keypoints,
    None: every described robot's) from the demonstrations' hand ``hand``."""
    hands = np.concatenate([d.hands[:, hand] for d in demos])
    mean, std = {}, {}
    for joint, (a, b, c) in (ALL_FLEXION if chains is None else chains).items():
        angles = flexion(hands, a, b, c)
        mean[joint] = float(angles.mean())
        std[joint] = float(max(angles.std(), MIN_STD))
    return mean, std


def teacher_prior(chains: dict[str, tuple[int, int, int]], task: str = "assembly", demos: int = 2, hand: int = 1
                  ) -> tuple[dict[str, float], dict[str, float]]:
    """hand_pose_prior of the SIMULATED scripted teacher's demonstrations (seeds 1..demos), what the
    trajopt service uses for a robot with fingers when no recorded demonstrations are given."""
    return hand_pose_prior([generate_demo(task, seed) for seed in range(1, demos + 1)], hand, chains)
