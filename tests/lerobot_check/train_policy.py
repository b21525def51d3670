"""Train LeRobot's Diffusion Policy a few steps on an export without cameras (run by
tests/unit/test_lerobot_export.py with .cache/lerobot-site and this directory on the path) and
print the losses as JSON.

The policy takes the keypoints (``observation.state``) and the object keypoints
(``observation.environment_state``) and predicts ``action``; LeRobot's ``LeRobotDataset`` serves
the windows its ``delta_timestamps`` ask for, its processors normalize with the export's stats."""

from __future__ import annotations

import json
import sys

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot.policies.diffusion.processor_diffusion import make_diffusion_pre_post_processors


def main(root: str, steps: int) -> None:
    torch.manual_seed(0)
    meta = LeRobotDatasetMetadata("local/crossmodal", root=root)
    feats = meta.features
    cfg = DiffusionConfig(
        n_obs_steps=2, horizon=8, n_action_steps=4, down_dims=(32, 64), diffusion_step_embed_dim=32,
        num_train_timesteps=20, device="cpu",
        input_features={
            "observation.state": PolicyFeature(FeatureType.STATE, tuple(feats["observation.state"]["shape"])),
            "observation.environment_state": PolicyFeature(
                FeatureType.ENV, tuple(feats["observation.environment_state"]["shape"]))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, tuple(feats["action"]["shape"]))})
    dt = 1.0 / meta.fps
    delta = {"observation.state": [i * dt for i in cfg.observation_delta_indices],
             "observation.environment_state": [i * dt for i in cfg.observation_delta_indices],
             "action": [i * dt for i in cfg.action_delta_indices]}
    ds = LeRobotDataset("local/crossmodal", root=root, delta_timestamps=delta, video_backend="pyav")
    policy = DiffusionPolicy(cfg)
    pre, _post = make_diffusion_pre_post_processors(cfg, dataset_stats=meta.stats)
    opt = torch.optim.Adam(policy.parameters(), lr=1e-3)
    loader = torch.utils.data.DataLoader(ds, batch_size=16, shuffle=True, num_workers=0)
    losses = []
    batches = iter(loader)
    for _ in range(steps):
        batch = pre(next(batches))
        loss, _ = policy.forward(batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    first = ds[0]
    print(json.dumps({"losses": losses, "state_window": list(first["observation.state"].shape),
                      "action_window": list(first["action"].shape),
                      "action_is_pad": first["action_is_pad"].tolist()}))


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 5)
