"""Baselines of thesis Table 7.1 behind the common ``Method`` interface (fit / rollout).

One module per family: naive replay (10), DMP (5), ProMP (6, 7), Diffusion Policy (8: LeRobot's
U-Net, lerobot_diffusion.py; 9: the reference transformer, diffusion_policy.py).
``make(name, quick)`` builds one by its table name. Rows (3) single state and (4) time window are
presets of our own network (learning/presets.py), built by evaluation.evaluate.make_method.
"""

from __future__ import annotations

from evaluation.baselines.diffusion_policy import DiffusionConfig, DiffusionPolicy
from evaluation.baselines.dmp import DMPBaseline
from evaluation.baselines.lerobot_diffusion import LeRobotDiffusion, LeRobotDiffusionSettings
from evaluation.baselines.promp import ProMPBaseline
from services.policy.naive import NaiveReplay

BASELINES = ("dmp", "promp_conditional", "promp_simple", "diffusion_unet", "diffusion_transformer", "naive")


def make(name: str, quick: bool = False, seed: int = 0):
    """A fresh, unfitted baseline by its Table 7.1 name; ``quick`` shrinks training to a smoke test."""
    if name == "naive":  # the node's own naive replay (services/policy/naive.py)
        return NaiveReplay()
    if name == "dmp":
        return DMPBaseline()
    if name in ("promp_conditional", "promp_simple"):
        return ProMPBaseline(conditional=name == "promp_conditional")
    if name == "diffusion_unet":  # LeRobot's DiffusionPolicy
        return LeRobotDiffusion(LeRobotDiffusionSettings.preset(quick=quick, seed=seed))
    if name == "diffusion_transformer":
        return DiffusionPolicy(DiffusionConfig.preset(quick=quick, seed=seed))
    raise KeyError(f"unknown baseline {name!r}; known: {', '.join(BASELINES)}")
