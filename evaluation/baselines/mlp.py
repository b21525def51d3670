"""Table 7.1 rows (3) single state and (4) time window.

Row (3) is the thesis's own network without tactile and memory (the ``single_state`` preset of
learning/presets.py). Row (4) is ``StateMLP``: a dense 2048-512-512-512 ReLU network mapping the
flat keypoint state, its velocity and window averages of the 16 samples before (over 8, 4, 2, 1, 1
samples) to keypoint velocities, trained with the thesis's exponentially scaled denoising (7.6-7.7)
and integrated step by step at inference.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from learning.ours import Ours
from learning.presets import PRESETS, Recipe
from services.policy.flat_state import BaselineError, check_train, flat_state, split_state
from shared.demo import Demo

WINDOW_SPLITS = (8, 4, 2, 1, 1)  # older -> newer, 16 samples in all


def window_averages(x: np.ndarray, t: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """(len(t), 5, D): means of the 16 samples before and including t over 8,4,2,1,1 samples,
    indices clamped at the episode start."""
    start = np.zeros_like(t) if start is None else start
    parts, back = [], sum(WINDOW_SPLITS)
    for n in WINDOW_SPLITS:
        idx = np.maximum(t[:, None] - back + 1 + np.arange(n)[None], start[:, None])
        parts.append(x[idx].mean(axis=1))
        back -= n
    return np.stack(parts, axis=1)


def quick_budget(recipe: Recipe, quick: bool) -> Recipe:
    """``recipe`` with the tiny --quick training budget (a smoke test), or as it is."""
    return recipe.replace(steps=5, hidden=(32, 32), batch=32) if quick else recipe


def make_state_policy(name: str, quick: bool = False, seed: int = 0) -> Ours | StateMLP:
    """Row (3): the single-state preset of the thesis's own network; row (4): ``StateMLP`` with the
    time window."""
    if name in PRESETS:
        return Ours(quick_budget(PRESETS[name], quick))
    return StateMLP(window=name == "time_window", quick=quick, seed=seed)


class StateMLP:
    """Row (4) time window (and a single-state variant without the window; see module docstring)."""

    def __init__(self, window: bool = False, hidden: tuple[int, ...] = (2048, 512, 512, 512), steps: int = 2000,
                 batch: int = 256, lr: float = 1e-3, noise_exponent: tuple[float, float] = (-3.3, -1.3),
                 noise_gain: float = 4.0, quick: bool = False, seed: int = 0) -> None:
        self.window = window
        self.name = "time_window" if window else "single_state"
        self.hidden, self.steps, self.batch, self.lr = hidden, steps, batch, lr
        if quick:
            self.hidden, self.steps, self.batch = (32, 32), 5, 32
        self.noise_exponent, self.noise_gain, self.seed = noise_exponent, noise_gain, seed
        self.net: nn.Module | None = None

    def _features(self, x: np.ndarray, v: np.ndarray, win: np.ndarray | None) -> np.ndarray:
        f = [x, v * 0.2]
        if win is not None:  # window averages relative to the current state: translation invariant
            f.append((win - x[:, None]).reshape(len(x), -1))
        return np.concatenate(f, axis=1)

    def fit(self, train: list[Demo], progress: bool = True) -> None:
        check_train(train)
        torch.manual_seed(self.seed)
        rng = np.random.default_rng(self.seed)
        self.dt = train[0].dt
        xs, vs, tgt, ts, starts, off = [], [], [], [], [], 0
        for demo in train:
            x = flat_state(demo)
            v = np.zeros_like(x)
            v[1:] = (x[1:] - x[:-1]) / demo.dt  # what a causal observer sees
            xs.append(x[:-1])
            vs.append(v[:-1])
            tgt.append((x[1:] - x[:-1]) / demo.dt)
            ts.append(off + np.arange(len(x) - 1))
            starts.append(np.full(len(x) - 1, off))
            off += len(x) - 1
        X, V, Y = np.concatenate(xs), np.concatenate(vs), np.concatenate(tgt)
        t_all, s_all = np.concatenate(ts), np.concatenate(starts)
        win = window_averages(X, t_all, s_all) if self.window else None
        self.x_mean, self.x_std = X.mean(0), X.std(0) + 1e-3
        self.y_scale = np.abs(Y).max(0) + 1e-3
        feats0 = self._features(X, V, win)
        self.f_mean, self.f_std = feats0.mean(0), feats0.std(0) + 1e-3
        layers, width = [], feats0.shape[1]
        for h in self.hidden:
            layers += [nn.Linear(width, h), nn.ReLU()]
            width = h
        self.net = nn.Sequential(*layers, nn.Linear(width, Y.shape[1]))
        opt = torch.optim.Adam(self.net.parameters(), lr=self.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, self.steps)
        t0 = time.perf_counter()
        for _ in tqdm(range(self.steps), desc=f"train {self.name}", disable=not progress, leave=False):
            i = rng.integers(0, len(X), self.batch)
            # 7.6-7.7: noise on the input positions, subtracted (times a gain) from the target velocity
            scale = 10.0 ** rng.uniform(*self.noise_exponent, (len(i), 1))
            noise = rng.normal(0, 1, X[i].shape) * scale
            xb = X[i] + noise
            f = self._features(xb, V[i], None if win is None else win[i])
            y = (Y[i] - noise * self.noise_gain) / self.y_scale
            pred = self.net(torch.from_numpy(((f - self.f_mean) / self.f_std).astype(np.float32)))
            loss = ((pred - torch.from_numpy(y.astype(np.float32))) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
        self.train_seconds = time.perf_counter() - t0
        self.net.eval()

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        if self.net is None:
            raise BaselineError(f"fit() {self.name} first")
        hist = [flat_state(start)[0]]
        v = np.zeros_like(hist[0])
        with torch.no_grad():
            for _ in range(steps - 1):
                x = hist[-1][None]
                recent = np.array(hist[-16:])
                win = window_averages(recent, np.array([len(recent) - 1])) if self.window else None
                f = self._features(x, v[None], win)
                out = self.net(torch.from_numpy(((f - self.f_mean) / self.f_std).astype(np.float32)))[0].numpy()
                v = out * self.y_scale
                hist.append(hist[-1] + v * self.dt)
        return split_state(np.array(hist))
