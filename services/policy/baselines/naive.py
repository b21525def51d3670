"""Table 7.1 row (10), the naive baseline: replay the training demonstration whose start state
is nearest to the observed one, time-aligned from the start of the episode (pure).

Also usable live: ``plan(observed_state_flat, t, steps)`` picks the demonstration at t == 0 (or
on the first call) and afterwards returns the chosen demonstration's states from time t on.
"""

from __future__ import annotations

import numpy as np

from services.policy.baselines.common import BaselineError, check_train, flat_state, hold_to, split_state
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

    def plan(self, observed_state_flat: np.ndarray, t: float, steps: int) -> np.ndarray:
        """(steps, D) flat states of the chosen demo from episode time t (seconds) on, at its dt.

        At t <= 0, or when nothing has been chosen yet, the demo nearest to the observation is chosen."""
        if self.chosen is None or t <= 0:
            self.chosen = self.nearest(observed_state_flat)
        x = self.states[self.chosen]
        first = int(np.clip(round(t / self.dt), 0, len(x) - 1))
        return hold_to(x[first:], steps)

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        x0 = flat_state(start)[0]  # the start state, occlusions filled from later observations
        return split_state(self.plan(x0, 0.0, steps))
