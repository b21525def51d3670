"""Hand-pose prior for the regulariser of thesis 7.22.

The thesis takes joint means and deviations from a hand pose dataset; we take them from
demonstrations: the flexion angle at each finger joint (angle between consecutive bones of the
21-keypoint hand) over all demonstration frames, mapped to the robot's finger joints by its
description's ``finger_flexion`` (shared/robots). The trajopt service reads the table shipped in
``models/hand_prior.json`` (``load_prior``); ``python -m learning.hand_prior`` writes it from the
scripted teacher's demonstrations, so no service runs the simulated teacher.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from shared.demo import HAND_NAMES, Demo
from shared.robots.registry import REGISTRY

DEFAULT_PRIOR = Path(__file__).resolve().parents[2] / "models" / "hand_prior.json"
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


def prior_table(demos: list[Demo], source: str) -> dict:
    """The table ``load_prior`` reads: per hand, every described robot's finger joints."""
    table: dict = {"source": source, "frames": int(sum(len(d.hands) for d in demos))}
    for hand, name in enumerate(HAND_NAMES):
        mean, std = hand_pose_prior(demos, hand)
        table[name] = {"mean": mean, "std": std}
    return table


def load_prior(chains: dict[str, tuple[int, int, int]], hand: str, path: str | Path = DEFAULT_PRIOR
               ) -> tuple[dict[str, float], dict[str, float]]:
    """Mean and deviation of the joints ``chains`` names for ``hand`` ("left"/"right") from the table
    at ``path``; ValueError naming what is missing and how to write the table."""
    hint = "write it with `python -m learning.hand_prior`"
    try:
        table = json.loads(Path(path).read_text())
        stats = table[hand]
        mean = {j: float(stats["mean"][j]) for j in chains}
        std = {j: float(stats["std"][j]) for j in chains}
    except FileNotFoundError as exc:
        raise ValueError(f"no hand-pose prior at {path}: {hint}") from exc
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"hand-pose prior {path} lacks {exc} for the {hand} hand: {hint}") from exc
    return mean, std
