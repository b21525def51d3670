"""Table 7.1 row (8): LeRobot's DiffusionPolicy behind the adapter (our keypoints in, the next
keypoints out; LeRobot's config defaults, training step and chunked action selection)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from evaluation.baselines import make
from evaluation.baselines.lerobot_diffusion import LeRobotDiffusion, LeRobotDiffusionSettings, windows
from evaluation.task_measure import predicted_touch
from interop import lerobot_site
from services.policy.flat_state import BaselineError, flat_state
from tests.unit.policy_demos import synthetic_protocol

torch.set_num_threads(1)
needs_lerobot = pytest.mark.skipif(not (lerobot_site.LEROBOT_SITE / "lerobot").is_dir(),
                                   reason=f"LeRobot is not installed beside the venv: {lerobot_site.INSTALL}")


@pytest.fixture(scope="module")
def demos():
    return synthetic_protocol(train=3, validation=2, steps=40)


def test_windows_are_served_as_lerobot_serves_delta_timestamps():
    x = np.arange(10, dtype=np.float32)[:, None] * np.ones((1, 2), np.float32)
    obs, act, pad = windows(x, [-1, 0], list(range(-1, 15)), drop_last=7)
    assert obs.shape == (3, 2, 2) and act.shape == (3, 16, 2)  # start frames 0..2: the last 7 left out
    np.testing.assert_array_equal(obs[0, :, 0], [0, 0])  # before the start the first frame repeats
    np.testing.assert_array_equal(obs[2, :, 0], [1, 2])
    # the action of frame t is the state of frame t + 1; outside the episode the edge repeats, padded
    np.testing.assert_array_equal(act[1, :, 0], [1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 9, 9, 9, 9, 9])
    assert pad[0, 0] and not pad[0, 1:10].any() and pad[0, 11:].all()
    np.testing.assert_array_equal(pad[1], np.arange(-1, 15) + 1 >= 10)


@needs_lerobot
def test_the_preset_changes_only_the_documented_lerobot_defaults():
    lerobot_site.use_lerobot()
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig  # beside the venv

    settings = LeRobotDiffusionSettings.preset()
    default = DiffusionConfig()
    assert set(settings.changes) == {"down_dims", "noise_scheduler_type", "num_inference_steps", "prediction_type"}
    assert default.down_dims == (512, 1024, 2048) and default.noise_scheduler_type == "DDPM"
    assert (default.horizon, default.n_obs_steps, default.n_action_steps, default.prediction_type) == \
        (16, 2, 8, "epsilon")
    cfg = LeRobotDiffusion(settings)._config(150)
    assert cfg.down_dims == (64, 128, 256) and cfg.num_inference_steps == 10 and cfg.prediction_type == "sample"
    assert (cfg.diffusion_step_embed_dim, cfg.optimizer_lr, cfg.scheduler_warmup_steps) == \
        (default.diffusion_step_embed_dim, default.optimizer_lr, default.scheduler_warmup_steps)


@needs_lerobot
def test_a_tiny_budget_trains_rolls_out_and_records_its_validation_curve(demos, tmp_path):
    policy = make("diffusion_unet", quick=True)
    policy.settings = replace(policy.settings, iterations=30, eval_every=15,
                              changes={**policy.settings.changes, "optimizer_lr": 1e-3})
    calls = []
    policy.monitor = lambda p: calls.append(len(p.losses)) or {"hand": 0.1, "object": 0.2, "hand_masked": 0.1,
                                                               "object_masked": 0.2}
    policy.fit(demos[:3], progress=False)
    assert np.mean(policy.losses[-5:]) < np.mean(policy.losses[:5])
    assert calls == [15, 30] and [c["iteration"] for c in policy.curve] == [15, 30]
    hands, objects = policy.rollout(demos[3], 23)
    assert hands.shape == (23, 2, 21, 3) and objects.shape == (23, 4, 3) and np.isfinite(hands).all()
    np.testing.assert_allclose(hands[0], flat_state(demos[3])[0, :126].reshape(2, 21, 3), atol=1e-6)
    policy.save_curve(tmp_path / "c.json", tmp_path / "c.png")
    saved = json.loads((tmp_path / "c.json").read_text())
    assert saved["config"]["lerobot_defaults_changed"]["down_dims"] == [16, 32] and len(saved["curve"]) == 2


@needs_lerobot
def test_each_action_is_the_next_state(demos):
    policy = make("diffusion_unet", quick=True)
    policy.fit(demos[:3], progress=False)
    start = flat_state(demos[3])[0].astype(np.float32)
    target = start + np.float32(0.01)  # every keypoint 1 cm further along x, y and z
    calls = []

    def select_action(batch):  # LeRobot's contract: normalised observations in, a normalised action out
        calls.append(batch["observation.state"].shape)
        x = torch.from_numpy(start[None])
        return policy.pre({"observation.state": x, "observation.environment_state": x[:, 126:],
                           "action": torch.from_numpy(target[None])})["action"]

    policy.net.select_action = select_action
    (hands, objects), = policy.rollout_batch([demos[3]], 6)
    assert predicted_touch(policy, demos[3], 6) is None  # no touch: its force comes from the positions
    assert len(calls) == 5 and calls[0] == (1, policy.dim)
    np.testing.assert_allclose(hands[0].ravel(), start[:126])
    np.testing.assert_allclose(hands[1:].reshape(5, -1), np.broadcast_to(target[:126], (5, 126)), atol=1e-5)
    np.testing.assert_allclose(objects[1:].reshape(5, -1), np.broadcast_to(target[126:], (5, 12)), atol=1e-5)


@needs_lerobot
def test_a_diverging_loss_is_refused(demos, monkeypatch):
    lerobot_site.use_lerobot()
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy  # beside the venv

    monkeypatch.setattr(DiffusionPolicy, "forward", lambda self, batch: (torch.tensor(float("nan")), None))
    with pytest.raises(BaselineError, match="training loss became nan"):
        make("diffusion_unet", quick=True).fit(demos[:3], progress=False)


def test_lerobot_missing_is_a_baseline_error_with_the_install_command(demos, monkeypatch, tmp_path):
    monkeypatch.setattr(lerobot_site, "LEROBOT_SITE", tmp_path / "none")
    with pytest.raises(BaselineError, match="pip install --target .cache/lerobot-site"):
        make("diffusion_unet", quick=True).fit(demos[:3], progress=False)


def test_rollout_before_fit_is_refused(demos):
    with pytest.raises(BaselineError, match="fit"):
        LeRobotDiffusion().rollout(demos[0], 5)
