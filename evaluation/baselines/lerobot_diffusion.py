"""Table 7.1 row (8): LeRobot's ``DiffusionPolicy`` (the 1-D U-Net of Chi et al. 2023) on our
keypoint observations, through a thin adapter (docs/baselines.md).

LeRobot's own code does the learning: its ``DiffusionConfig`` defaults, its ``DiffusionPolicy``
(U-Net, noise scheduler, loss, chunked ``select_action``), its normalising processors
(``make_diffusion_pre_post_processors``) and its optimizer and learning-rate presets with its
training loop's gradient clipping. The adapter only maps data in and out, as LeRobot's dataset
would serve our export (docs/lerobot.md) with no cameras:

- ``observation.state``: the flat 3-D keypoints (hands then objects, occlusions interpolated);
  ``observation.environment_state``: the object keypoints (LeRobot's state-only policies need it);
- ``action``: the keypoints one frame later (the last frame repeats);
- windows as ``LeRobotDataset`` serves ``delta_timestamps`` (indices outside an episode clamped
  to its edge, ``action_is_pad`` set there), start frames as LeRobot's episode-aware sampler draws
  them (the last ``drop_n_last_frames`` of an episode left out);
- rollout: ``select_action`` from the current state, its action is the next state.

``LeRobotDiffusionSettings.changes`` holds what differs from LeRobot's defaults (the CPU budget).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from evaluation.baselines.curve import record, save_curve
from interop.lerobot_site import LeRobotMissingError, use_lerobot
from services.policy.flat_state import HAND_DIMS, BaselineError, check_train, flat_state, split_state
from shared.demo import Demo

STATE, ENV, ACTION = "observation.state", "observation.environment_state", "action"


@dataclass(frozen=True)
class LeRobotDiffusionSettings:
    """The training budget and the ``DiffusionConfig`` fields changed from LeRobot's defaults."""

    iterations: int = 100_000  # LeRobot's TrainPipelineConfig defaults: 100k steps of batch 8
    batch: int = 8
    eval_every: int = 0  # > 0: score the policy on the validation rollouts this often (the curve)
    seed: int = 0
    changes: dict = field(default_factory=dict)

    @classmethod
    def preset(cls, quick: bool = False, seed: int = 0) -> LeRobotDiffusionSettings:
        """What Table 7.1 runs on a 2-core CPU (docs/baselines.md): the U-Net at an eighth of the
        default widths, DDIM with 10 steps on the same 100-step training schedule, batch 64, and the
        clean chunk as prediction target (a LeRobot option: at 64 channels the first level cannot
        carry the 150 noise values per step, and with the noise as target the loss stays at 1.0)."""
        cfg = cls(iterations=1000, batch=64, eval_every=250, seed=seed,
                  changes={"down_dims": (64, 128, 256), "noise_scheduler_type": "DDIM", "num_inference_steps": 10,
                           "prediction_type": "sample"})
        if quick:
            cfg = replace(cfg, iterations=5, batch=16, eval_every=0, changes={
                "down_dims": (16, 32), "diffusion_step_embed_dim": 16, "num_train_timesteps": 10,
                "noise_scheduler_type": "DDIM", "num_inference_steps": 5, "scheduler_warmup_steps": 1})
        return cfg


def windows(x: np.ndarray, obs_idx: list[int], act_idx: list[int], drop_last: int
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One episode's (N, n_obs, D) observation and (N, horizon, D) action windows and (N, horizon)
    pad flags, as LeRobotDataset serves them, for the start frames LeRobot's sampler draws."""
    T = len(x)
    act = x[np.minimum(np.arange(T) + 1, T - 1)]  # the keypoints one frame later
    t = np.arange(max(T - drop_last, 1))[:, None]
    oi, ai = t + np.asarray(obs_idx)[None], t + np.asarray(act_idx)[None]
    return x[np.clip(oi, 0, T - 1)], act[np.clip(ai, 0, T - 1)], (ai < 0) | (ai >= T)


def _stats(x: np.ndarray) -> dict[str, np.ndarray]:
    x = x.astype(np.float32)
    return {"min": x.min(0), "max": x.max(0), "mean": x.mean(0), "std": x.std(0), "count": np.array([len(x)])}


class LeRobotDiffusion:
    """The method interface (fit / rollout_batch / rollout) around LeRobot's DiffusionPolicy.
    ``monitor``: set by `xm eval` to a function scoring this policy on the validation rollouts;
    with ``eval_every`` > 0 it is called during training and ``curve`` records the scores."""

    name = "diffusion_unet"

    def __init__(self, settings: LeRobotDiffusionSettings | None = None) -> None:
        self.settings = settings or LeRobotDiffusionSettings()
        self.net = None  # LeRobot's DiffusionPolicy (not ``policy``: task_measure reads that as our net)
        self.losses: list[float] = []
        self.curve: list[dict] = []
        self.monitor = None
        self.train_seconds = 0.0

    def _config(self, dim: int):
        try:
            use_lerobot()
        except LeRobotMissingError as exc:
            raise BaselineError(f"{self.name}: {exc}") from exc
        # LeRobot lives beside the venv (interop/lerobot_site.py), so it is imported only here
        from lerobot.configs.types import FeatureType, PolicyFeature
        from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

        return DiffusionConfig(
            device="cpu", **self.settings.changes,
            input_features={STATE: PolicyFeature(FeatureType.STATE, (dim,)),
                            ENV: PolicyFeature(FeatureType.ENV, (dim - HAND_DIMS,))},
            output_features={ACTION: PolicyFeature(FeatureType.ACTION, (dim,))})

    def fit(self, train: list[Demo], progress: bool = True) -> None:
        """LeRobot's training step (loss, gradient clipping at its optimizer preset's norm, optimizer
        and cosine schedule presets) on random windows; BaselineError when the loss is not finite."""
        s = self.settings
        check_train(train)
        states = [flat_state(d).astype(np.float32) for d in train]
        self.dim = states[0].shape[1]
        cfg = self._config(self.dim)  # puts LeRobot on the path
        from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy  # beside the venv, as above
        from lerobot.policies.diffusion.processor_diffusion import make_diffusion_pre_post_processors

        obs, act, pad = (np.concatenate(a) for a in zip(*(windows(
            x, cfg.observation_delta_indices, cfg.action_delta_indices, cfg.drop_n_last_frames) for x in states),
            strict=True))
        every = np.concatenate(states)
        nxt = np.concatenate([x[np.minimum(np.arange(len(x)) + 1, len(x) - 1)] for x in states])
        stats = {STATE: _stats(every), ENV: _stats(every[:, HAND_DIMS:]), ACTION: _stats(nxt)}
        torch.manual_seed(s.seed)
        rng = np.random.default_rng(s.seed)
        self.net = DiffusionPolicy(cfg)
        self.pre, self.post = make_diffusion_pre_post_processors(cfg, dataset_stats=stats)
        opt_cfg = cfg.get_optimizer_preset()
        opt = opt_cfg.build(self.net.get_optim_params())
        sched = cfg.get_scheduler_preset().build(opt, s.iterations)
        obs_t, act_t, pad_t = torch.from_numpy(obs), torch.from_numpy(act), torch.from_numpy(pad)
        t0 = time.perf_counter()
        self.net.train()
        for it in range(s.iterations):
            idx = torch.from_numpy(rng.integers(0, len(obs), s.batch))
            batch = self.pre({STATE: obs_t[idx], ENV: obs_t[idx][..., HAND_DIMS:], ACTION: act_t[idx],
                              "action_is_pad": pad_t[idx]})
            loss, _ = self.net.forward(batch)
            if not torch.isfinite(loss):
                raise BaselineError(f"{self.name}: training loss became {loss.item()} at iteration {it}")
            loss.backward()
            torch.nn.utils.clip_grad_norm_(self.net.parameters(), opt_cfg.grad_clip_norm)
            opt.step()
            opt.zero_grad()
            sched.step()
            self.losses.append(loss.item())
            done = it + 1
            if self.monitor is not None and s.eval_every > 0 and (done % s.eval_every == 0 or done == s.iterations):
                self.net.eval()
                t0 = record(self, done, s.eval_every, t0)
                self.net.train()
        self.net.eval()
        self.train_seconds = time.perf_counter() - t0

    @torch.no_grad()
    def rollout_batch(self, starts: list[Demo], steps: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """Roll out from several start states at once: LeRobot's ``select_action`` (a chunk of
        ``horizon`` predicted every ``n_action_steps``), each action taken as the next state."""
        if self.net is None:
            raise BaselineError(f"fit() {self.name} first")
        x = np.stack([flat_state(s)[0] for s in starts]).astype(np.float32)
        if x.shape[1] != self.dim:
            raise BaselineError(f"start state has {x.shape[1]} values, the policy {self.dim}")
        traj = [x]
        self.net.reset()
        with torch.random.fork_rng():  # sampling noise of its own: a rollout during training leaves its batches
            torch.manual_seed(self.settings.seed + 1)
            while len(traj) < steps:
                cur = torch.from_numpy(traj[-1])
                action = self.net.select_action(self.pre({STATE: cur, ENV: cur[:, HAND_DIMS:]}))
                traj.append(self.post(action).numpy().astype(np.float32))
        return [split_state(xi) for xi in np.stack(traj, axis=1).astype(float)]

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        return self.rollout_batch([start], steps)[0]

    def save_curve(self, json_path, png_path) -> None:
        config = {"lerobot_defaults_changed": self.settings.changes, "iterations": self.settings.iterations,
                  "batch": self.settings.batch, "eval_every": self.settings.eval_every, "seed": self.settings.seed}
        save_curve(self.name, config, self.curve, json_path, png_path)
