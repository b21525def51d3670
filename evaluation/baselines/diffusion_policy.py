"""Table 7.1 rows (8) and (9): Diffusion Policy (Chi et al. 2023) in its low-dimensional form,
through a thin adapter on our keypoint demonstrations.

The diffusion process, the learning-rate schedule and the weight average are diffusers' own
(``DDPMScheduler``, ``get_cosine_schedule_with_warmup``, ``EMAModel``) with the reference configs'
settings; the networks are the reference architectures (diffusion_nets.py). LeRobot's
``DiffusionPolicy`` does not install beside this project's pins (docs/baselines.md). The adapter
maps data in and out: observations are the flat 3-D keypoint state (hands and objects, occlusions
interpolated) of the last ``n_obs_steps`` samples, actions the keypoint velocities of a
``horizon``-step chunk, both min-max normalised to [-1, 1] as the reference's "limits"
normaliser does; ``n_action_steps`` of each chunk are integrated into the state before the next
prediction. ``DiffusionConfig.reference`` holds the reference defaults; ``DiffusionConfig.preset``
is what a 2-core CPU affords (the differences are listed in docs/baselines.md).
"""

from __future__ import annotations

import copy
import json
import sys
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

from evaluation.baselines.diffusion_nets import ConditionalUnet1D, TransformerForDiffusion
from services.policy.flat_state import BaselineError, check_train, flat_state, split_state
from shared.demo import Demo


@dataclass(frozen=True)
class DiffusionConfig:
    """Defaults: the reference low-dimensional U-Net config (train_diffusion_unet_lowdim_workspace)."""

    model: str = "unet"  # "unet" | "transformer"
    horizon: int = 16
    n_obs_steps: int = 2
    n_action_steps: int = 8
    train_timesteps: int = 100
    inference_steps: int = 100  # == train_timesteps: DDPM as the reference; fewer: DDIM on the same model
    prediction: str = "epsilon"  # the scheduler's prediction_type: "epsilon" | "sample"
    down_dims: tuple[int, ...] = (256, 512, 1024)
    kernel: int = 5
    groups: int = 8
    step_embed: int = 256
    n_layer: int = 8  # transformer
    n_head: int = 4
    n_emb: int = 256
    p_drop_attn: float = 0.01
    lr: float = 1e-4
    weight_decay: float = 1e-6
    betas: tuple[float, float] = (0.95, 0.999)
    warmup: int = 500
    iterations: int = 100_000  # the reference: 5000 epochs of batch 256
    batch: int = 256
    ema_power: float = 0.75
    ema_max: float = 0.9999
    eval_every: int = 0  # > 0: score the averaged weights on the validation rollouts this often (the curve)
    seed: int = 0

    @classmethod
    def reference(cls, model: str) -> DiffusionConfig:
        """The reference defaults of the low-dimensional U-Net or (push-T) transformer config."""
        if model == "unet":
            return cls()
        if model == "transformer":
            return cls(model="transformer", weight_decay=0.1, betas=(0.9, 0.95), warmup=1000)
        raise ValueError(f"unknown diffusion model {model!r} (unet or transformer)")

    @classmethod
    def preset(cls, model: str, quick: bool = False, seed: int = 0) -> DiffusionConfig:
        """The CPU budget of Table 7.1 here (docs/baselines.md): the reference nets at reduced width,
        a smaller batch and fewer iterations, DDIM sampling, and the clean chunk as the prediction
        target (a reference option; with the noise as target neither net learns within this budget)."""
        cfg = cls.reference(model)
        cfg = replace(cfg, down_dims=(64, 128, 256), step_embed=64, n_layer=4, n_emb=128, prediction="sample",
                      iterations=1500, batch=64, warmup=150, inference_steps=10, eval_every=250, seed=seed)
        if quick:
            cfg = replace(cfg, down_dims=(16, 32), step_embed=16, n_layer=1, n_emb=32, iterations=5, batch=16,
                          train_timesteps=10, inference_steps=5, warmup=1, eval_every=0)
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
    """The method interface (fit / rollout_batch / rollout) around the reference Diffusion Policy.
    ``monitor``: set by `xm eval` to a function scoring this policy on the validation rollouts;
    with ``eval_every`` > 0 it is called during training and ``curve`` records the scores."""

    def __init__(self, config: DiffusionConfig | None = None) -> None:
        self.cfg = config or DiffusionConfig()
        self.name = f"diffusion_{self.cfg.model}"
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
        if cfg.model == "unet":
            return ConditionalUnet1D(dim, cfg.n_obs_steps * dim, tuple(cfg.down_dims), cfg.kernel, cfg.groups,
                                     cfg.step_embed)
        if cfg.model == "transformer":
            return TransformerForDiffusion(dim, dim, cfg.horizon, cfg.n_obs_steps, cfg.n_layer, cfg.n_head,
                                           cfg.n_emb, p_drop_attn=cfg.p_drop_attn)
        raise BaselineError(f"unknown diffusion model {cfg.model!r} (unet or transformer)")

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
        groups = model.param_groups(cfg.weight_decay) if hasattr(model, "param_groups") else \
            [{"params": list(model.parameters()), "weight_decay": cfg.weight_decay}]
        opt = torch.optim.AdamW(groups, lr=cfg.lr, betas=cfg.betas, eps=1e-8)
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
                t_eval = time.perf_counter()
                self.curve.append({"iteration": done, "loss": float(np.mean(self.losses[-cfg.eval_every:])),
                                   "train_s": t_eval - t0, **self.monitor(self)})
                t0 += time.perf_counter() - t_eval  # train_s counts training only
                print(f"{self.name} {json.dumps(self.curve[-1])}", file=sys.stderr, flush=True)  # a long run's trace
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
        json_path.write_text(json.dumps({"method": self.name, "config": asdict(self.cfg), "curve": self.curve},
                                        indent=2))
        import matplotlib  # optional heavy dependency, loaded only to draw the curve

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        it = [c["iteration"] for c in self.curve]
        fig, ax = plt.subplots(figsize=(6, 4))
        for key in ("hand", "object", "hand_masked", "object_masked"):
            ax.plot(it, [c[key] * 1e3 for c in self.curve], "o-", label=key.replace("_", " "))
        ax.set_xlabel("training iteration")
        ax.set_ylabel("validation closest-point distance (mm)")
        ax.set_yscale("log")
        ax.set_title(f"{self.name}: validation rollouts of the averaged weights")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(png_path, dpi=100)
        plt.close(fig)
