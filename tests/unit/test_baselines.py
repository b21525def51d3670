from __future__ import annotations

import numpy as np
import pytest
import torch

from evaluation.baselines import BASELINES, make
from evaluation.baselines.diffusion import DiffusionConfig, DiffusionPolicy, cosine_alpha_bar
from services.policy.flat_state import BaselineError, flat_state, interpolate_occluded, raw_state
from services.policy.naive import NaiveReplay
from tests.unit.policy_demos import synthetic_demo, synthetic_protocol

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def demos():
    return synthetic_protocol(train=3, validation=2, steps=40)


@pytest.mark.parametrize("name", BASELINES)
def test_every_baseline_fits_and_rolls_out(name, demos):
    train, val = demos[:3], demos[3:]
    method = make(name, quick=True)
    method.fit(train, progress=False)
    for demo, steps in ((val[0], 40), (val[1], 23)):
        hands, objects = method.rollout(demo, steps)
        assert hands.shape == (steps, 2, 21, 3)
        assert objects.shape == (steps, 4, 3)
        assert np.isfinite(hands).all() and np.isfinite(objects).all()


@pytest.mark.parametrize("name", ["dmp", "promp_conditional", "naive", "diffusion_unet"])
def test_rollout_before_fit_is_refused(name, demos):
    with pytest.raises(BaselineError):
        make(name, quick=True).rollout(demos[0], 5)


def test_naive_replays_a_training_demo_exactly_from_its_start():
    train = [synthetic_demo(i, occlude=False) for i in range(3)]
    method = NaiveReplay()
    method.fit(train, progress=False)
    for demo in train:
        hands, objects = method.rollout(demo, demo.steps)
        np.testing.assert_array_equal(hands, demo.hands.astype(float))
        np.testing.assert_array_equal(objects, demo.objects.astype(float))


def test_naive_with_occlusions_matches_every_observed_sample_and_plans_live():
    train = synthetic_protocol(train=3, validation=0)
    method = NaiveReplay()
    method.fit(train, progress=False)
    demo = train[2]
    hands, _ = method.rollout(demo, demo.steps)
    seen = demo.hand_mask.astype(bool)
    np.testing.assert_array_equal(hands[seen], demo.hands[seen].astype(float))
    # live: a NaN (unobserved) entry is ignored when choosing, later calls keep the choice
    obs = raw_state(demo)[0].copy()
    obs[:30] = np.nan
    plan0 = method.plan(obs, 0.0, 5)
    assert method.chosen == 2
    np.testing.assert_array_equal(plan0, flat_state(demo)[:5])
    later = method.plan(raw_state(train[0])[10], 10 * demo.dt, 100)
    assert method.chosen == 2  # not re-chosen mid-episode
    np.testing.assert_array_equal(later[0], flat_state(demo)[10])
    np.testing.assert_array_equal(later[-1], flat_state(demo)[-1])  # held at the end


def test_conditional_promp_starts_at_the_start_state_simple_does_not(demos):
    train, val = demos[:3], demos[3:]
    x0 = flat_state(val[0])[0]
    cond, simple = make("promp_conditional"), make("promp_simple")
    cond.fit(train, progress=False)
    simple.fit(train, progress=False)
    hc, oc = cond.rollout(val[0], 40)
    hs, os_ = simple.rollout(val[0], 40)
    start_c = np.concatenate([hc[0].ravel(), oc[0].ravel()])
    start_s = np.concatenate([hs[0].ravel(), os_[0].ravel()])
    assert np.abs(start_c - x0).max() < np.abs(start_s - x0).max()
    assert np.abs(start_c - x0).max() < 0.01


def test_dmp_starts_at_the_start_state_and_ends_at_the_demo_goal(demos):
    train, val = demos[:3], demos[3:]
    dmp = make("dmp")
    dmp.fit(train, progress=False)
    hands, objects = dmp.rollout(val[0], 40)
    x = np.concatenate([hands.reshape(40, -1), objects.reshape(40, -1)], axis=1)
    np.testing.assert_allclose(x[0], flat_state(val[0])[0], atol=1e-6)
    assert np.abs(x[-1] - flat_state(train[0])[-1]).max() < 0.02


def test_interpolation_fills_occluded_samples_linearly():
    x = np.array([[0.0], [9.0], [9.0], [3.0], [9.0]])
    m = np.array([[1], [0], [0], [1], [0]], bool)
    np.testing.assert_allclose(interpolate_occluded(x, m)[:, 0], [0, 1, 2, 3, 3])


def test_rows_of_our_network_are_not_baselines_and_unknown_names_fail():
    """Rows (3)-(4) are presets of our network (evaluation.evaluate.make_method); nothing here
    stands in for them."""
    for name in ("single_state", "time_window", "mlp"):
        with pytest.raises(KeyError, match="unknown baseline"):
            make(name)


def test_cosine_schedule_is_monotone_and_ends_near_zero():
    ab = cosine_alpha_bar(100)
    assert np.all(np.diff(ab) < 0) and ab[0] > 0.99 and ab[-1] < 1e-3


class _Oracle(torch.nn.Module):
    """The exact noise predictor for a data distribution concentrated on one action sequence."""

    def __init__(self, target: torch.Tensor, alpha_bar: np.ndarray) -> None:
        super().__init__()
        self.target, self.ab = target, torch.from_numpy(alpha_bar).float()

    def forward(self, x, t, obs):
        ab = self.ab[t][:, None, None]
        return (x - ab.sqrt() * self.target) / (1 - ab).sqrt()


class _SampleOracle(torch.nn.Module):
    """The exact clean-chunk predictor for the same one-sequence distribution."""

    def __init__(self, target: torch.Tensor) -> None:
        super().__init__()
        self.target = target

    def forward(self, x, t, obs):
        return self.target.expand_as(x)


@pytest.mark.parametrize("prediction", ["epsilon", "sample"])
@pytest.mark.parametrize("inference_steps", [100, 10])
def test_ddpm_and_ddim_samplers_recover_the_data_with_an_exact_model(inference_steps, prediction, demos):
    cfg = DiffusionConfig(inference_steps=inference_steps, prediction=prediction)
    policy = DiffusionPolicy(cfg)
    policy._windows(demos[:3])  # sets the normalisers
    policy.dim = 138
    policy.alpha_bar = cosine_alpha_bar(100)
    target = torch.rand(cfg.horizon, policy.dim) * 1.6 - 0.8
    policy.model = _Oracle(target, policy.alpha_bar) if prediction == "epsilon" else _SampleOracle(target)
    out = policy.sample(np.zeros((3, 2, policy.dim)), torch.Generator().manual_seed(0))
    np.testing.assert_allclose(out, np.broadcast_to(target.numpy(), out.shape), atol=1e-3)


def test_rollout_integrates_the_executed_velocities_in_chunks(demos):
    policy = DiffusionPolicy(DiffusionConfig(inference_steps=10))
    policy._windows(demos[:3])
    policy.dim, policy.dt = 138, demos[0].dt
    policy.alpha_bar = cosine_alpha_bar(100)
    v = np.zeros(policy.dim)
    v[0] = 0.05  # left wrist x at 5 cm/s
    target = torch.from_numpy(policy.act_norm(np.tile(v, (16, 1)))).float()
    policy.model = _Oracle(target, policy.alpha_bar)
    (hands, objects), (hands2, _) = policy.rollout_batch(demos[3:5], 21)
    assert hands.shape == (21, 2, 21, 3) and objects.shape == (21, 4, 3)
    np.testing.assert_allclose(hands[:, 0, 0, 0] - hands[0, 0, 0, 0], 0.05 * policy.dt * np.arange(21), atol=1e-4)
    np.testing.assert_allclose(hands[:, 1], np.broadcast_to(hands[0, 1], hands[:, 1].shape), atol=1e-4)
    np.testing.assert_allclose(hands2[0], flat_state(demos[4])[0, :126].reshape(2, 21, 3))


def test_diffusion_training_reduces_the_loss(demos):
    policy = make("diffusion_transformer", quick=True)
    policy.cfg.iterations, policy.cfg.lr = 40, 1e-3
    policy.fit(demos[:3], progress=False)
    assert np.mean(policy.losses[-10:]) < np.mean(policy.losses[:10])


def test_clean_chunk_prediction_learns_where_noise_prediction_stalls(demos):
    # the same small transformer, data and budget: predicting the 16 x 150 noise it is given stays
    # near the trivial loss of 1, predicting the clean chunk (low rank) falls far below its start
    losses = {}
    for prediction in ("epsilon", "sample"):
        policy = make("diffusion_transformer", quick=True)
        policy.cfg.iterations, policy.cfg.lr, policy.cfg.prediction = 60, 1e-3, prediction
        policy.fit(demos[:3], progress=False)
        losses[prediction] = (np.mean(policy.losses[:5]), np.mean(policy.losses[-10:]))
    assert losses["epsilon"][1] > 0.5
    assert losses["sample"][1] < 0.5 * losses["sample"][0]
    assert losses["sample"][1] < 0.5 * losses["epsilon"][1]
    assert make("diffusion_unet").cfg.prediction == "sample"
    policy.cfg.prediction = "noise"  # a misspelt target is refused, not run as epsilon
    with pytest.raises(BaselineError, match="prediction target"):
        policy.fit(demos[:3], progress=False)


def test_unet_passes_every_action_value_through():
    # 8 x 6 action values against a 4 x 8 bottleneck (horizon/2 x first width): with the
    # full-resolution skip (8 x 8) the noise prediction can depend on every input value
    from evaluation.baselines.diffusion_nets import ConditionalUnet1D

    torch.manual_seed(0)
    net = ConditionalUnet1D(action_dim=6, cond_dim=6, down_dims=(8, 16), kernel=3, groups=4, step_embed=8)
    t, obs, x = torch.tensor([5]), torch.randn(1, 2, 3), torch.randn(1, 8, 6)
    jac = torch.autograd.functional.jacobian(lambda a: net(a.reshape(1, 8, 6), t, obs).reshape(-1), x.reshape(-1))
    sv = torch.linalg.svdvals(jac)
    assert (sv > 1e-5 * sv[0]).sum() > 4 * 8  # more directions than the half-resolution level can carry


def test_unknown_baseline():
    with pytest.raises(KeyError):
        make("nope")
