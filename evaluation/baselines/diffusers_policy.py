"""Diffusion Policy on diffusers' DDPM scheduler: the thin adapter between our keypoint demonstrations
and a reference noise-prediction network (a sketch for Table 7.1 rows 8-9; not a row yet).

LeRobot's DiffusionPolicy cannot be installed beside this project's pins (docs/baselines.md), so
the diffusion process comes from diffusers (``DDPMScheduler`` with the reference implementation's
defaults: 100 training steps, squared-cosine schedule, epsilon prediction, predicted x0 clipped
to [-1, 1], "fixed small" variance) and the adapter only maps data in and out: observations are the
flat keypoint state of the last ``n_obs_steps`` samples (low-dimensional, no images), actions the
keypoint velocities of a ``horizon``-step chunk, both min-max normalised to [-1, 1] (the windows
and normalisers of diffusion.py); ``n_action_steps`` of each chunk are integrated into the state
before the next prediction. The network is diffusion_nets.ConditionalUnet1D until the reference
1-D U-Net replaces it.
"""

from __future__ import annotations

import copy
import time

import numpy as np
import torch
from diffusers.schedulers.scheduling_ddpm import DDPMScheduler

from evaluation.baselines.diffusion import DiffusionConfig, DiffusionPolicy
from services.policy.flat_state import BaselineError, check_train
from shared.demo import Demo


def reference_scheduler(cfg: DiffusionConfig) -> DDPMScheduler:
    """The noise scheduler of Chi et al.'s low-dimensional configs, as diffusers builds it."""
    return DDPMScheduler(num_train_timesteps=cfg.train_timesteps, beta_schedule="squaredcos_cap_v2",
                         clip_sample=True, prediction_type=cfg.prediction, variance_type="fixed_small")


class DiffusersPolicy(DiffusionPolicy):
    """``DiffusionPolicy``'s data handling and rollout with diffusers' scheduler for noising and sampling."""

    def __init__(self, config: DiffusionConfig | None = None) -> None:
        super().__init__(config)
        self.name = f"diffusers_{self.cfg.model}"
        self.scheduler = reference_scheduler(self.cfg)

    def fit(self, train: list[Demo], progress: bool = True) -> None:
        """AdamW on the denoising loss of uniformly drawn scheduler steps; the EMA weights are kept."""
        cfg = self.cfg
        check_train(train)
        torch.manual_seed(cfg.seed)
        rng = np.random.default_rng(cfg.seed)
        self.dt = train[0].dt
        obs, act = (torch.from_numpy(a.astype(np.float32)) for a in self._windows(train))
        self.dim = obs.shape[-1]
        model = self._build(self.dim)
        opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay)
        ema = copy.deepcopy(model).eval()
        t0 = time.perf_counter()
        model.train()
        for it in range(cfg.iterations):
            idx = torch.from_numpy(rng.integers(0, len(obs), cfg.batch))
            a, o = act[idx], obs[idx]
            noise = torch.randn_like(a)
            k = torch.randint(0, cfg.train_timesteps, (len(a),))
            target = a if cfg.prediction == "sample" else noise
            loss = torch.nn.functional.mse_loss(model(self.scheduler.add_noise(a, noise, k), k, o), target)
            if not torch.isfinite(loss):
                raise BaselineError(f"{self.name}: training loss became {loss.item()} at iteration {it}")
            opt.zero_grad()
            loss.backward()
            opt.step()
            decay = min(max(1 - (1 + it) ** -cfg.ema_power, 0.0), cfg.ema_max)
            with torch.no_grad():
                for pe, pm in zip(ema.parameters(), model.parameters(), strict=True):
                    pe.lerp_(pm.detach(), 1 - decay)
            self.losses.append(loss.item())
        self.train_seconds = time.perf_counter() - t0
        self.model = ema

    @torch.no_grad()
    def sample(self, obs: np.ndarray, generator: torch.Generator | None = None) -> np.ndarray:
        """Normalised obs windows (B, n_obs, D) -> normalised action chunks (B, horizon, D) by the
        scheduler's ancestral steps."""
        if self.model is None:
            raise BaselineError(f"fit() {self.name} first")
        o = torch.from_numpy(obs.astype(np.float32))
        x = torch.randn((len(obs), self.cfg.horizon, self.dim), generator=generator)
        self.scheduler.set_timesteps(self.cfg.inference_steps)
        for t in self.scheduler.timesteps:
            out = self.model(x, torch.full((len(x),), int(t)), o)
            x = self.scheduler.step(out, t, x, generator=generator).prev_sample
        return x.numpy()
