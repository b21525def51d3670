"""The diffusers adapter sketch for Diffusion Policy (evaluation/baselines/diffusers_policy.py):
diffusers' scheduler is the process diffusion.py writes by hand, it samples the data back with an
exact model, and a tiny budget trains and rolls out."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evaluation.baselines.diffusers_policy import DiffusersPolicy, reference_scheduler
from evaluation.baselines.diffusion import DiffusionConfig, cosine_alpha_bar
from services.policy.flat_state import BaselineError
from tests.unit.policy_demos import synthetic_protocol

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def demos():
    return synthetic_protocol(train=3, validation=2, steps=40)


def test_the_reference_scheduler_is_the_squared_cosine_schedule():
    sched = reference_scheduler(DiffusionConfig())
    np.testing.assert_allclose(sched.alphas_cumprod.double().numpy(), cosine_alpha_bar(100), rtol=1e-4)  # float32
    assert sched.config.prediction_type == "epsilon" and sched.config.clip_sample


class _Oracle(torch.nn.Module):
    """The exact noise predictor for data concentrated on one action chunk."""

    def __init__(self, target: torch.Tensor, alpha_bar: torch.Tensor) -> None:
        super().__init__()
        self.target, self.ab = target, alpha_bar.float()

    def forward(self, x, t, obs):
        ab = self.ab[t][:, None, None]
        return (x - ab.sqrt() * self.target) / (1 - ab).sqrt()


@pytest.mark.parametrize("inference_steps", [100, 10])
def test_sampling_recovers_the_data_with_an_exact_model(demos, inference_steps):
    policy = DiffusersPolicy(DiffusionConfig(inference_steps=inference_steps))
    policy._windows(demos[:3])
    policy.dim = 138
    target = torch.rand(policy.cfg.horizon, policy.dim) * 1.6 - 0.8
    policy.model = _Oracle(target, policy.scheduler.alphas_cumprod)
    out = policy.sample(np.zeros((3, 2, policy.dim)), torch.Generator().manual_seed(0))
    np.testing.assert_allclose(out, np.broadcast_to(target.numpy(), out.shape), atol=1e-3)


def test_a_tiny_budget_trains_and_rolls_out(demos):
    cfg = DiffusionConfig.preset("unet", quick=True)
    cfg.iterations, cfg.lr = 30, 1e-3
    policy = DiffusersPolicy(cfg)
    with pytest.raises(BaselineError):
        policy.sample(np.zeros((1, 2, 138)))
    policy.fit(demos[:3], progress=False)
    assert np.isfinite(policy.losses).all() and np.mean(policy.losses[-5:]) < np.mean(policy.losses[:5])
    hands, objects = policy.rollout(demos[3], 20)
    assert hands.shape == (20, 2, 21, 3) and objects.shape == (20, 4, 3)
    assert np.isfinite(hands).all() and np.isfinite(objects).all()
