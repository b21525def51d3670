"""The chapter-7 policy: augmentations, every variant trains and rolls out finite, checkpoints."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from services.policy import features as F
from services.policy.ours import PRESETS, Ours, PolicyConfig, PolicyError
from services.world.teacher import generate_demo


@pytest.fixture(scope="module")
def demos():
    return [generate_demo("assembly", s, index=i) for i, s in enumerate((11, 12))]


def test_mirror_swaps_hands_and_preserves_distances(demos):
    d = demos[0]
    m = F.mirror(d)
    assert m.meta["grasp_hand"] != d.meta["grasp_hand"]
    np.testing.assert_allclose(m.hands[:, 0, :, 1], -d.hands[:, 1, :, 1])
    dist = np.linalg.norm(d.hands[:, 0, 8] - d.objects[:, 0], axis=-1)
    np.testing.assert_allclose(np.linalg.norm(m.hands[:, 1, 8] - m.objects[:, 0], axis=-1), dist, rtol=1e-5)


def test_features_are_translation_invariant_and_rotation_covariant(demos):
    d = demos[0]
    f = F.state_features(d.hands[5], d.objects[5], np.zeros((2, 21, 3)), np.zeros_like(d.objects[5]))
    shift = np.array([0.1, -0.2, 0.0])
    g = F.state_features(d.hands[5] + shift, d.objects[5] + shift, np.zeros((2, 21, 3)), np.zeros_like(d.objects[5]))
    np.testing.assert_allclose(f, g, atol=1e-5)
    p = np.random.default_rng(0).normal(size=(4, 3))
    r = F.rotate_z(p, np.array(0.7))
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), np.linalg.norm(p, axis=1))
    np.testing.assert_allclose(r[:, 2], p[:, 2])


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_every_variant_trains_and_rolls_out_finite(demos, preset, tmp_path):
    torch.set_num_threads(1)
    cfg = PRESETS[preset]
    method = Ours(PolicyConfig(**{**cfg.__dict__, "steps": 5, "batch": 32, "hidden": (64, 32)}))
    method.fit(demos[:1], progress=False)
    assert np.isfinite(method.losses).all()
    hands, objects = method.rollout(demos[1], 30)
    assert hands.shape == (30, 2, 21, 3) and objects.shape == (30, len(demos[1].object_names), 3)
    assert np.isfinite(hands).all() and np.isfinite(objects).all()
    path = tmp_path / "p.pt"
    method.save(str(path))
    torch.load(path, weights_only=True)  # no pickle needed
    again = Ours.load(str(path))
    h2, _ = again.rollout(demos[1], 30)
    np.testing.assert_allclose(h2, hands, atol=1e-5)


def test_nan_output_never_leaves_the_policy(demos):
    method = Ours(PolicyConfig(name="x", tactile=False, memory=False, steps=2, batch=8, hidden=(16,)))
    method.fit(demos[:1], progress=False)
    with torch.no_grad():
        method.net.head.bias.fill_(float("nan"))
    with pytest.raises(PolicyError):
        method.rollout(demos[1], 3)
