"""Table 7.1 rows (6) and (7): probabilistic movement primitives (movement_primitives.promp.ProMP)
over the flat keypoint state, learned from all training demonstrations.

The library's EM ``imitate`` builds dense (dims*steps)^2 matrices (60000^2 here), so the weight
distribution is estimated directly: per-demonstration weights by the library's ridge regression
(``ProMP.weights``, one dimension at a time: the basis is block diagonal), then their mean and
covariance over demonstrations, plus a small isotropic prior so that the covariance is full rank
with only three demonstrations. (6) conditions that joint distribution on the validation start
state (``condition_position`` at t=0), so object positions move the hand trajectories through
the learned correlations; (7) returns the mean trajectory. Time is normalised per demonstration;
the primitive runs for the mean training duration.
"""

from __future__ import annotations

import numpy as np
from movement_primitives.promp import ProMP

from services.policy.flat_state import BaselineError, check_train, flat_state, hold_to, split_state
from shared.demo import Demo


class ProMPBaseline:
    def __init__(self, conditional: bool, weights_per_dim: int = 10, prior_std: float = 0.01,
                 start_std: float = 0.001) -> None:
        self.conditional = conditional
        self.weights_per_dim = weights_per_dim
        self.prior_std = prior_std  # metres: spread allowed beyond what the demonstrations show
        self.start_std = start_std  # metres: how closely the conditioned start is matched
        self.name = "promp_conditional" if conditional else "promp_simple"
        self.promp = None

    def fit(self, train: list[Demo], progress: bool = True) -> None:
        check_train(train)
        one = ProMP(1, n_weights_per_dim=self.weights_per_dim)
        ws = []
        for demo in train:
            y = flat_state(demo)
            t = np.linspace(0.0, 1.0, demo.steps)
            ws.append(np.concatenate([one.weights(t.copy(), y[:, j:j + 1]) for j in range(y.shape[1])]))
        w = np.array(ws)  # (demos, dims * weights), dimension-major like the library's layout
        self.dims = y.shape[1]
        mean = w.mean(axis=0)
        dev = w - mean
        cov = dev.T @ dev / max(len(w) - 1, 1) + self.prior_std ** 2 * np.eye(w.shape[1])
        self.promp = ProMP(self.dims, n_weights_per_dim=self.weights_per_dim).from_weight_distribution(mean, cov)
        self.steps = int(round(np.mean([d.steps for d in train])))

    def _trajectory(self, weight_mean: np.ndarray) -> np.ndarray:
        # one dimension at a time: the library's n-D basis would be a dense (dims*w, dims*steps) matrix
        one = ProMP(1, n_weights_per_dim=self.weights_per_dim)
        t = np.linspace(0.0, 1.0, self.steps)
        w = weight_mean.reshape(self.dims, self.weights_per_dim)
        return np.stack([one.trajectory_from_weights(t.copy(), w[j])[:, 0] for j in range(self.dims)], axis=1)

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        if self.promp is None:
            raise BaselineError("fit() the ProMP first")
        promp = self.promp
        if self.conditional:
            x0 = flat_state(start)[0]
            if x0.shape[0] != self.dims:
                raise BaselineError(f"start state has {x0.shape[0]} values, the ProMP {self.dims}")
            promp = promp.condition_position(x0, y_cov=self.start_std ** 2 * np.eye(self.dims), t=0.0, t_max=1.0)
        return split_state(hold_to(self._trajectory(promp.weight_mean), steps))
