"""The rollout interface every policy of Table 7.1 implements (ours and the baselines)."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from shared.demo import Demo


class Method(Protocol):
    name: str

    def fit(self, train: list[Demo], progress: bool = True) -> None: ...

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        """Neural-simulation rollout from start's first state (positions of hands and objects at t=0, and any
        masks/tactile at t=0): returns predicted hands (steps,2,21,3) and objects (steps,K,3)."""
        ...
