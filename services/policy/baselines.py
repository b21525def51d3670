"""Baselines of Table 7.1 behind the same fit/rollout interface (rows 5-7 here; 3, 4, 10 elsewhere).

State vector: all hand and object keypoints flattened (observations = 3-D keypoints, as the
thesis did). Occluded samples are interpolated before fitting ([55] in the thesis).
Row (5) DMP: one training demonstration, started from the validation start state, goal kept.
Row (6) conditional ProMP: all training demonstrations, conditioned on the start state.
Row (7) simple ProMP: the mean trajectory of the training demonstrations.
Diffusion Policy (rows 8, 9) is not implemented yet.
"""

from __future__ import annotations

import numpy as np

from shared.demo import Demo


def flat_state(demo: Demo) -> np.ndarray:
    """(T, D) hands then objects, with occluded samples linearly interpolated over time."""
    x = np.concatenate([demo.hands.reshape(demo.steps, -1), demo.objects.reshape(demo.steps, -1)], axis=1)
    mask = np.concatenate([np.repeat(demo.hand_mask.reshape(demo.steps, -1), 3, axis=1),
                           np.repeat(demo.object_mask, 3, axis=1)], axis=1).astype(bool)
    t = np.arange(demo.steps)
    out = x.astype(float).copy()
    for j in np.flatnonzero(~mask.all(axis=0)):
        seen = mask[:, j]
        if seen.any():
            out[:, j] = np.interp(t, t[seen], x[seen, j])
    return out


def split_state(x: np.ndarray, demo: Demo) -> tuple[np.ndarray, np.ndarray]:
    nh = 2 * 21 * 3
    return x[:, :nh].reshape(len(x), 2, 21, 3), x[:, nh:].reshape(len(x), -1, 3)


def _resample(x: np.ndarray, steps: int) -> np.ndarray:
    src = np.linspace(0, 1, len(x))
    dst = np.linspace(0, 1, steps)
    return np.stack([np.interp(dst, src, x[:, j]) for j in range(x.shape[1])], axis=1)


class DMPBaseline:
    name = "dmp"

    def __init__(self, weights: int = 10) -> None:
        self.weights = weights

    def fit(self, train: list[Demo], progress: bool = True) -> None:
        from movement_primitives.dmp import DMP

        demo = train[0]
        self.y = flat_state(demo)
        self.dt = demo.dt
        self.T = np.arange(demo.steps) * demo.dt
        self.dmp = DMP(self.y.shape[1], execution_time=self.T[-1], dt=demo.dt, n_weights_per_dim=self.weights)
        self.dmp.imitate(self.T, self.y)

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        self.dmp.configure(start_y=flat_state(start)[0], goal_y=self.y[-1])
        _, y = self.dmp.open_loop()
        return split_state(_resample(np.asarray(y), steps), start)


class ProMPBaseline:
    """One ProMP per state dimension (a full joint covariance over 150 dimensions does not fit in
    memory); conditioning on the start value works per dimension."""

    def __init__(self, conditional: bool, weights: int = 10) -> None:
        self.conditional = conditional
        self.weights = weights
        self.name = "promp_conditional" if conditional else "promp_simple"

    def fit(self, train: list[Demo], progress: bool = True) -> None:
        from movement_primitives.promp import ProMP

        steps = max(d.steps for d in train)
        ys = np.stack([_resample(flat_state(d), steps) for d in train])
        ts = np.tile(np.linspace(0, 1, steps), (len(train), 1))
        self.promps = []
        for j in range(ys.shape[2]):
            promp = ProMP(1, n_weights_per_dim=self.weights)
            promp.imitate(ts, ys[:, :, j:j + 1], n_iter=50)
            self.promps.append(promp)

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        x0 = flat_state(start)[0]
        t = np.linspace(0, 1, steps)
        cols = []
        for j, promp in enumerate(self.promps):
            if self.conditional:
                promp = promp.condition_position(np.array([x0[j]]), y_cov=np.array([[1e-6]]), t=0.0, t_max=1.0)
            cols.append(promp.mean_trajectory(t)[:, 0])
        return split_state(np.stack(cols, axis=1), start)
