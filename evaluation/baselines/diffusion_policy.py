"""Table 7.1 row (9): the Diffusion Policy transformer (Chi et al. 2023, low-dimensional form)
through a thin adapter on our keypoint demonstrations.

LeRobot has no transformer Diffusion Policy (its ``DiffusionPolicy`` is the 1-D U-Net, row (8),
lerobot_diffusion.py), so this row is the reference repository's ``TransformerForDiffusion``
(diffusion_nets.py) with diffusers' diffusion process, learning-rate schedule and weight average
(``DDPMScheduler``, ``get_cosine_schedule_with_warmup``, ``EMAModel``) at the reference config's
settings. The adapter maps data in and out: observations are the flat 3-D keypoint state (hands and
objects, occlusions interpolated) of the last ``n_obs_steps`` samples, actions the keypoint
velocities of a ``horizon``-step chunk, both min-max normalised to [-1, 1] as the reference's
"limits" normaliser does; ``n_action_steps`` of each chunk are integrated into the state before
the next prediction. ``DiffusionConfig.reference()`` holds the reference defaults;
``DiffusionConfig.preset`` is what a 2-core CPU affords (docs/baselines.md).
"""

from __future__ import annotations

import copy
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from diffusers.optimization import get_cosine_schedule_with_warmup
from diffusers.schedulers.scheduling_ddim import DDIMScheduler
from diffusers.schedulers.scheduling_ddpm import DDPMScheduler
from diffusers.training_utils import EMAModel
from tqdm import tqdm

from evaluation.baselines.curve import record, save_curve
from evaluation.baselines.diffusion_nets import TransformerForDiffusion
from services.policy.flat_state import BaselineError, check_train, flat_state, split_state
from shared.demo import Demo


@dataclass(frozen=True)
class DiffusionConfig:
    """Defaults: the reference push-T low-dimensional transformer config."""

    horizon: int = 16
    n_obs_steps: int = 2
    n_action_steps: int = 8
    train_timesteps: int = 100
    inference_steps: int = 100  # == train_timesteps: DDPM as the reference; fewer: DDIM on the same model
    prediction: str = "epsilon"  # the scheduler's prediction_type: "epsilon" | "sample"
    n_layer: int = 8
    n_head: int = 4
    n_emb: int = 256
    p_drop_attn: float = 0.01
    lr: float = 1e-4
    weight_decay: float = 0.1
    betas: tuple[float, float] = (0.9, 0.95)
    warmup: int = 1000
    iterations: int = 100_000  # the reference: 8000 epochs of batch 256
    batch: int = 256
    ema_power: float = 0.75
    ema_max: float = 0.9999
    eval_every: int = 0  # > 0: score the averaged weights on the validation rollouts this often (the curve)
    seed: int = 0

    @classmethod
    def reference(cls) -> DiffusionConfig:
        """The reference defaults of the (push-T) low-dimensional transformer config."""
        return cls()

    @classmethod
    def preset(cls, quick: bool = False, seed: int = 0) -> DiffusionConfig:
        """The CPU budget of Table 7.1 here (docs/baselines.md): the reference net at reduced width,
        a smaller batch and fewer iterations, DDIM sampling, and the clean chunk as the prediction
        target (a reference option; with the noise as target the net does not learn within this budget)."""
        cfg = replace(cls.reference(), n_layer=4, n_emb=128, prediction="sample", iterations=1500, batch=64,
                      warmup=150, inference_steps=10, eval_every=250, seed=seed)
        if quick:
            cfg = replace(cfg, n_layer=1, n_emb=32, iterations=5, batch=16, train_timesteps=10, inference_steps=5,
                          warmup=1, eval_every=0)
        return cfg


class Normalizer:
    """Per-dimension min-max map to [-1, 1]; (nearly) constant dimensions are only centred."""

    def __init__(self, x: np.ndarray) -> None:
        lo, hi = x.min(axis=0), x.max(axis=0)
        span = hi - lo
        self.scale = np.where(span > 1e-4, 2.0 / np.maximum(span, 1e-12), 1.0)
        self.offset = np.where(span > 1e-4, -1.0 - lo * self.scale, -0.5 * (lo + hi))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return x * self.scale + self.offset

    def inverse(self, y: np.ndarray) -> np.ndarray:
        return (y - self.offset) / self.scale


def reference_scheduler(cfg: DiffusionConfig) -> DDPMScheduler:
    """The noise scheduler of the reference low-dimensional configs, as diffusers builds it."""
    return DDPMScheduler(num_train_timesteps=cfg.train_timesteps, beta_start=1e-4, beta_end=0.02,
                         beta_schedule="squaredcos_cap_v2", variance_type="fixed_small", clip_sample=True,
                         prediction_type=cfg.prediction)


class DiffusionPolicy:
    """The method interface (fit / rollout_batch / rollout) around the reference Diffusion Policy
    transformer.
    ``monitor``: set by `xm eval` to a function scoring this policy on the validation rollouts;
    with ``eval_every`` > 0 it is called during training and ``curve`` records the scores."""

    def __init__(self, config: DiffusionConfig | None = None) -> None:
        self.cfg = config or DiffusionConfig()
        self.name = "diffusion_transformer"
        self.scheduler = reference_scheduler(self.cfg)
        self.model: torch.nn.Module | None = None
        self.losses: list[float] = []
        self.curve: list[dict] = []
        self.monitor = None
        self.train_seconds = 0.0

    # --- data ---------------------------------------------------------------------------
    def _windows(self, train: list[Demo]) -> tuple[np.ndarray, np.ndarray]:
        """Normalised (N, n_obs, D) observation windows and (N, horizon, D) action windows.
        Before the start the first state repeats (zero velocity); after the end the velocity is 0."""
        cfg = self.cfg
        obs, act = [], []
        for demo in train:
            x = flat_state(demo)
            v = np.zeros_like(x)
            v[:-1] = (x[1:] - x[:-1]) / demo.dt  # executing v[t] from x[t] lands on x[t+1]
            T = len(x)
            s = np.arange(T - 1)[:, None] - (cfg.n_obs_steps - 1)
            oi = np.clip(s + np.arange(cfg.n_obs_steps)[None], 0, T - 1)
            ai = s + np.arange(cfg.horizon)[None]
            valid = (ai >= 0) & (ai < T)
            obs.append(x[oi])
            act.append(np.where(valid[..., None], v[np.clip(ai, 0, T - 1)], 0.0))
        obs_all, act_all = np.concatenate(obs), np.concatenate(act)
        self.obs_norm = Normalizer(obs_all.reshape(-1, obs_all.shape[-1]))
        self.act_norm = Normalizer(act_all.reshape(-1, act_all.shape[-1]))
        return self.obs_norm(obs_all), self.act_norm(act_all)

    def _build(self, dim: int) -> torch.nn.Module:
        cfg = self.cfg
        return TransformerForDiffusion(dim, dim, cfg.horizon, cfg.n_obs_steps, cfg.n_layer, cfg.n_head, cfg.n_emb,
                                       p_drop_attn=cfg.p_drop_attn)

    # --- training -----------------------------------------------------------------------
    def fit(self, train: list[Demo], progress: bool = True) -> None:
        """AdamW on the denoising loss of uniformly drawn scheduler steps, cosine learning rate with
        warm-up, EMA weights kept; BaselineError when the loss is not finite."""
        cfg = self.cfg
        check_train(train)
        torch.manual_seed(cfg.seed)
        rng = np.random.default_rng(cfg.seed)
        self.dt = train[0].dt
        obs, act = (torch.from_numpy(a.astype(np.float32)) for a in self._windows(train))
        self.dim = obs.shape[-1]
        model = self._build(self.dim)
        opt = torch.optim.AdamW(model.param_groups(cfg.weight_decay), lr=cfg.lr, betas=cfg.betas, eps=1e-8)
        sched = get_cosine_schedule_with_warmup(opt, cfg.warmup, cfg.iterations)
        ema = EMAModel(model.parameters(), decay=cfg.ema_max, use_ema_warmup=True, inv_gamma=1.0,
                       power=cfg.ema_power)
        self.model = copy.deepcopy(model).eval()  # holds the averaged weights
        t0 = time.perf_counter()
        bar = tqdm(range(cfg.iterations), desc=f"train {self.name}", disable=not progress, leave=False)
        model.train()
        for it in bar:
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
            sched.step()
            ema.step(model.parameters())
            self.losses.append(loss.item())
            if it % 20 == 0:
                bar.set_postfix(loss=f"{np.mean(self.losses[-20:]):.4f}")
            done = it + 1
            if self.monitor is not None and cfg.eval_every > 0 and (done % cfg.eval_every == 0
                                                                    or done == cfg.iterations):
                ema.copy_to(self.model.parameters())
                t0 = record(self, done, cfg.eval_every, t0)
        ema.copy_to(self.model.parameters())
        self.train_seconds = time.perf_counter() - t0

    # --- inference ----------------------------------------------------------------------
    def _sampler(self) -> DDPMScheduler | DDIMScheduler:
        if self.cfg.inference_steps >= self.cfg.train_timesteps:
            return self.scheduler
        return DDIMScheduler.from_config(self.scheduler.config)

    @torch.no_grad()
    def sample(self, obs: np.ndarray, generator: torch.Generator | None = None) -> np.ndarray:
        """Normalised obs windows (B, n_obs, D) -> normalised action chunks (B, horizon, D) by the
        scheduler's steps (DDPM ancestral, or DDIM with fewer steps)."""
        if self.model is None:
            raise BaselineError(f"fit() {self.name} first")
        o = torch.from_numpy(obs.astype(np.float32))
        x = torch.randn((len(obs), self.cfg.horizon, self.dim), generator=generator)
        sampler = self._sampler()
        sampler.set_timesteps(self.cfg.inference_steps)
        for t in sampler.timesteps:
            out = self.model(x, torch.full((len(x),), int(t)), o)
            x = sampler.step(out, t, x, generator=generator).prev_sample
        return x.numpy()

    def rollout_batch(self, starts: list[Demo], steps: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """Roll out from several start states at once (one network call per denoising step for all)."""
        if self.model is None:
            raise BaselineError("fit() the diffusion policy first")
        cfg = self.cfg
        x0 = np.stack([flat_state(s)[0] for s in starts])
        if x0.shape[1] != self.dim:
            raise BaselineError(f"start state has {x0.shape[1]} values, the policy {self.dim}")
        gen = torch.Generator().manual_seed(cfg.seed + 1)
        traj = [x0]
        hist = [x0] * cfg.n_obs_steps  # the first observation repeats, as in training
        while len(traj) < steps:
            obs = self.obs_norm(np.stack(hist[-cfg.n_obs_steps:], axis=1))
            act = self.act_norm.inverse(self.sample(obs, gen).astype(float))
            first = cfg.n_obs_steps - 1
            for v in np.moveaxis(act[:, first:first + cfg.n_action_steps], 1, 0):
                if len(traj) >= steps:
                    break
                traj.append(traj[-1] + v * self.dt)
                hist.append(traj[-1])
        x = np.stack(traj, axis=1)  # (B, steps, D)
        return [split_state(xi) for xi in x]

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        return self.rollout_batch([start], steps)[0]

    def save_curve(self, json_path: Path, png_path: Path) -> None:
        """The validation curve (scores of the averaged weights against iterations) and the config."""
        save_curve(self.name, asdict(self.cfg), self.curve, json_path, png_path)
