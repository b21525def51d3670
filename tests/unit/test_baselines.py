from __future__ import annotations

import numpy as np
import pytest
import torch

from evaluation.baselines import BASELINES, make
from interop import lerobot_site
from services.policy.flat_state import BaselineError, flat_state, interpolate_occluded, raw_state
from services.policy.naive import NaiveReplay
from tests.unit.policy_demos import synthetic_demo, synthetic_protocol

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def demos():
    return synthetic_protocol(train=3, validation=2, steps=40)


@pytest.mark.parametrize("name", BASELINES)
def test_every_baseline_fits_and_rolls_out(name, demos):
    if name == "diffusion_unet" and not (lerobot_site.LEROBOT_SITE / "lerobot").is_dir():
        pytest.skip(f"LeRobot is not installed beside the venv: {lerobot_site.INSTALL}")
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


def test_unknown_baseline():
    with pytest.raises(KeyError):
        make("nope")
