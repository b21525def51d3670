"""The thesis's naive baseline (Table 7.1, method 10): replay the training demonstration whose
start state is nearest to the observed one, time-aligned from the start of the episode (pure)."""

from __future__ import annotations

import numpy as np

from shared.demo import Demo


class NaiveReplay:
    name = "naive"

    def __init__(self) -> None:
        self.train: list[Demo] = []
        self.chosen: Demo | None = None

    def fit(self, train: list[Demo], progress: bool = True) -> None:
        if not train:
            raise ValueError("naive replay needs at least one training demonstration")
        self.train = list(train)

    def nearest(self, objects: np.ndarray, object_mask: np.ndarray | None = None) -> Demo:
        """The training demo whose first object keypoints are closest (masked points ignored)."""
        mask = np.ones(len(objects), bool) if object_mask is None else np.asarray(object_mask, bool)
        costs = [np.sum(np.linalg.norm(d.objects[0] - objects, axis=-1)[mask]) if d.objects.shape[1] == len(objects)
                 else np.inf for d in self.train]
        return self.train[int(np.argmin(costs))]

    def start(self, objects: np.ndarray, object_mask: np.ndarray | None = None) -> None:
        self.chosen = self.nearest(objects, object_mask)

    def plan(self, t: float, steps: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Hands (steps,2,21,3) and objects (steps,K,3) of the chosen demo from episode time t."""
        if self.chosen is None:
            raise RuntimeError("call start() with the episode's first observation before plan()")
        d = self.chosen
        idx = np.clip(np.round((t + dt * np.arange(steps)) / d.dt).astype(int), 0, d.steps - 1)
        return d.hands[idx], d.objects[idx]

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        self.start(start.objects[0], start.object_mask[0])
        d = self.chosen
        idx = np.minimum(np.arange(steps), d.steps - 1)
        return d.hands[idx].copy(), d.objects[idx].copy()
