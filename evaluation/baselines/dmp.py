"""Table 7.1 row (5): a dynamic movement primitive (movement_primitives.dmp.DMP) over the flat
keypoint state, imitated from one training demonstration (the first), started from the
validation start state with the demonstrated goal kept."""

from __future__ import annotations

import numpy as np
from movement_primitives.dmp import DMP

from services.policy.flat_state import BaselineError, check_train, flat_state, hold_to, split_state
from shared.demo import Demo


class DMPBaseline:
    name = "dmp"

    def __init__(self, weights_per_dim: int = 10, demo_index: int = 0) -> None:
        self.weights_per_dim = weights_per_dim
        self.demo_index = demo_index
        self.dmp = None

    def fit(self, train: list[Demo], progress: bool = True) -> None:
        check_train(train)
        demo = train[min(self.demo_index, len(train) - 1)]
        self.y = flat_state(demo)
        self.dt = demo.dt
        times = np.arange(demo.steps) * demo.dt
        self.dmp = DMP(self.y.shape[1], execution_time=float(times[-1]), dt=demo.dt,
                       n_weights_per_dim=self.weights_per_dim)
        self.dmp.imitate(times, self.y)

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        if self.dmp is None:
            raise BaselineError("fit() the DMP first")
        x0 = flat_state(start)[0]
        if x0.shape != self.y[0].shape:
            raise BaselineError(f"start state has {x0.shape[0]} values, the DMP {self.y.shape[1]}")
        self.dmp.configure(start_y=x0, goal_y=self.y[-1])
        _, y = self.dmp.open_loop()
        return split_state(hold_to(np.asarray(y), steps))
