"""Table 7.1 row (9): the reference Diffusion Policy transformer behind the adapter (diffusers'
scheduler, the reference network, our keypoint data in and out). Row (8), LeRobot's U-Net:
test_lerobot_diffusion.py."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from evaluation.baselines import make
from evaluation.baselines.diffusion_nets import TransformerForDiffusion
from evaluation.baselines.diffusion_policy import DiffusionConfig, DiffusionPolicy, reference_scheduler
from services.policy.flat_state import BaselineError, flat_state
from tests.unit.policy_demos import synthetic_protocol

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def demos():
    return synthetic_protocol(train=3, validation=2, steps=40)


def test_the_reference_scheduler_is_the_squared_cosine_schedule():
    sched = reference_scheduler(DiffusionConfig())
    f = [math.cos((i / 100 + 0.008) / 1.008 * math.pi / 2) ** 2 for i in range(101)]
    betas = [min(1 - f[i + 1] / f[i], 0.999) for i in range(100)]
    np.testing.assert_allclose(sched.alphas_cumprod.numpy(), np.cumprod(1 - np.array(betas)), rtol=1e-4)
    assert sched.config.clip_sample and sched.config.prediction_type == "epsilon"
    assert sched.config.variance_type == "fixed_small"


def test_reference_defaults_and_the_cpu_preset_differ_only_where_documented():
    ref, cpu = DiffusionConfig.reference(), DiffusionConfig.preset()
    assert (ref.horizon, ref.n_obs_steps, ref.n_action_steps, ref.train_timesteps, ref.inference_steps) == \
        (16, 2, 8, 100, 100)
    assert (ref.n_layer, ref.n_head, ref.n_emb, ref.lr, ref.batch) == (8, 4, 256, 1e-4, 256)
    assert (ref.weight_decay, ref.betas, ref.warmup) == (0.1, (0.9, 0.95), 1000)
    changed = {k for k in ref.__dataclass_fields__ if getattr(ref, k) != getattr(cpu, k)}
    assert changed == {"n_layer", "n_emb", "prediction", "iterations", "batch", "warmup", "inference_steps",
                       "eval_every"}


class _Oracle(torch.nn.Module):
    """The exact predictor for a data distribution concentrated on one action chunk."""

    def __init__(self, target: torch.Tensor, alphas_cumprod: torch.Tensor, prediction: str) -> None:
        super().__init__()
        self.target, self.ab, self.prediction = target, alphas_cumprod.float(), prediction

    def forward(self, x, t, obs):
        if self.prediction == "sample":
            return self.target.expand_as(x)
        ab = self.ab[t][:, None, None]
        return (x - ab.sqrt() * self.target) / (1 - ab).sqrt()


@pytest.mark.parametrize("prediction", ["epsilon", "sample"])
@pytest.mark.parametrize("inference_steps", [100, 10])
def test_ddpm_and_ddim_sampling_recover_the_data_with_an_exact_model(inference_steps, prediction, demos):
    policy = DiffusionPolicy(DiffusionConfig(inference_steps=inference_steps, prediction=prediction))
    policy._windows(demos[:3])
    policy.dim = 138
    target = torch.rand(16, policy.dim) * 1.6 - 0.8
    policy.model = _Oracle(target, policy.scheduler.alphas_cumprod, prediction)
    out = policy.sample(np.zeros((3, 2, policy.dim)), torch.Generator().manual_seed(0))
    np.testing.assert_allclose(out, np.broadcast_to(target.numpy(), out.shape), atol=2e-3)


def test_rollout_integrates_the_executed_velocities_in_chunks(demos):
    policy = DiffusionPolicy(DiffusionConfig(inference_steps=10))
    policy._windows(demos[:3])
    policy.dim, policy.dt = 138, demos[0].dt
    v = np.zeros(policy.dim)
    v[0] = 0.05  # left wrist x at 5 cm/s
    target = torch.from_numpy(policy.act_norm(np.tile(v, (16, 1)))).float()
    policy.model = _Oracle(target, policy.scheduler.alphas_cumprod, "epsilon")
    (hands, objects), (hands2, _) = policy.rollout_batch(demos[3:5], 21)
    assert hands.shape == (21, 2, 21, 3) and objects.shape == (21, 4, 3)
    np.testing.assert_allclose(hands[:, 0, 0, 0] - hands[0, 0, 0, 0], 0.05 * policy.dt * np.arange(21), atol=1e-3)
    np.testing.assert_allclose(hands[:, 1], np.broadcast_to(hands[0, 1], hands[:, 1].shape), atol=1e-3)
    np.testing.assert_allclose(hands2[0], flat_state(demos[4])[0, :126].reshape(2, 21, 3))


def test_a_tiny_budget_trains_rolls_out_and_records_its_validation_curve(demos, tmp_path):
    policy = make("diffusion_transformer", quick=True)
    policy.cfg = replace(policy.cfg, iterations=40, lr=1e-3, eval_every=20)
    calls = []
    policy.monitor = lambda p: calls.append(len(p.losses)) or {"hand": 0.1, "object": 0.2, "hand_masked": 0.1,
                                                               "object_masked": 0.2}
    policy.fit(demos[:3], progress=False)
    assert np.mean(policy.losses[-10:]) < np.mean(policy.losses[:10])
    assert calls == [20, 40] and [c["iteration"] for c in policy.curve] == [20, 40]
    hands, objects = policy.rollout(demos[3], 12)
    assert hands.shape == (12, 2, 21, 3) and np.isfinite(hands).all()
    policy.save_curve(tmp_path / "c.json", tmp_path / "c.png")
    saved = json.loads((tmp_path / "c.json").read_text())
    assert saved["method"] == "diffusion_transformer" and saved["config"]["n_layer"] == 1
    assert len(saved["curve"]) == 2 and (tmp_path / "c.png").stat().st_size


def test_a_diverging_loss_is_refused(demos):
    class Diverged(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.ones(1))

        def forward(self, x, t, obs):
            return x * self.w * float("nan")

        def param_groups(self, weight_decay):
            return [{"params": [self.w], "weight_decay": weight_decay}]

    policy = make("diffusion_transformer", quick=True)
    policy._build = lambda dim: Diverged()
    with pytest.raises(BaselineError, match="training loss became nan"):
        policy.fit(demos[:3], progress=False)


def test_the_transformer_keeps_the_reference_shape_and_is_causal():
    torch.manual_seed(0)
    x, t, obs = torch.randn(2, 16, 6), torch.tensor([3, 70]), torch.randn(2, 2, 3)
    tf = TransformerForDiffusion(6, 3, 16, 2, n_layer=1, n_head=2, n_emb=8)
    y = tf(x, t, obs)
    assert y.shape == x.shape and not torch.allclose(y, tf(x, t, obs + 1))
    x2 = x.clone()
    x2[:, 10:] += 1  # causal: later action tokens do not change earlier outputs
    torch.testing.assert_close(tf.eval()(x2, t, obs)[:, :10], tf(x, t, obs)[:, :10])
