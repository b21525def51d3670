"""The thesis's naive baseline (Table 7.1, method 10): replay the training demonstration whose
start state is nearest to the observed one, time-aligned from the start of the episode (pure).

The same object is row (10) of ``xm eval`` (``fit`` / ``rollout``) and the node's ``method =
"naive"`` (``plan`` on each observation: the demonstration is chosen at the episode start, or on
the first call, and afterwards its states from episode time t on are returned).
"""

from __future__ import annotations

import numpy as np

from services.policy.flat_state import BaselineError, check_train, flat_state, split_state
from shared.demo import Demo


class NaiveReplay:
    name = "naive"

    def __init__(self) -> None:
        self.states: list[np.ndarray] = []  # (T_i, D) interpolated flat states of the training demos
        self.dt = 0.0
        self.chosen: int | None = None

    def fit(self, train: list[Demo], progress: bool = True) -> None:
        check_train(train)
        self.states = [flat_state(d) for d in train]
        self.dt = train[0].dt

    def nearest(self, observed_state_flat: np.ndarray) -> int:
        """Index of the training demo whose first state is closest; NaN entries (unobserved) are ignored."""
        if not self.states:
            raise BaselineError("fit() the naive replay before asking for a plan")
        x = np.asarray(observed_state_flat, float).ravel()
        if x.shape[0] != self.states[0].shape[1]:
            raise BaselineError(f"observed state has {x.shape[0]} values, the demonstrations {self.states[0].shape[1]}")
        seen = np.isfinite(x)
        costs = [np.sum((s[0, seen] - x[seen]) ** 2) for s in self.states]
        return int(np.argmin(costs))

    def plan(self, observed_state_flat: np.ndarray, t: float, steps: int, dt: float | None = None) -> np.ndarray:
        """(steps, D) flat states of the chosen demo from episode time t (seconds) on, ``dt`` apart
        (default the demonstrations' own); past its end the last state is held.

        At t <= 0, or when nothing has been chosen yet, the demo nearest to the observation is chosen."""
        if self.chosen is None or t <= 0:
            self.chosen = self.nearest(observed_state_flat)
        x = self.states[self.chosen]
        if dt is None:
            first = int(np.clip(round(t / self.dt), 0, len(x) - 1))
            return x[np.minimum(first + np.arange(steps), len(x) - 1)]
        return x[np.clip(np.round((t + dt * np.arange(steps)) / self.dt).astype(int), 0, len(x) - 1)]

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        x0 = flat_state(start)[0]  # the start state, occlusions filled from later observations
        return split_state(self.plan(x0, 0.0, steps))
