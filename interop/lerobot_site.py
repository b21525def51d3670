"""LeRobot in this process: its package directory beside the venv on the import path.

LeRobot 0.4.4 cannot be installed into the venv (it pins torch < 2.11; docs/lerobot.md), so the
Makefile installs it with ``--no-deps`` into ``.cache/lerobot-site``, where the venv supplies torch,
numpy, diffusers and huggingface_hub. ``lerobot_shim/torchvision`` stands in for torchvision, whose
only wheels for this torch are CUDA builds that fail to import: LeRobot imports it at module level
for image augmentation and image encoders, which state-only use never calls.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LEROBOT_SITE = ROOT / ".cache" / "lerobot-site"
SHIM = Path(__file__).resolve().parent / "lerobot_shim"
INSTALL = (".venv/bin/pip install --target .cache/lerobot-site --no-deps -r tests/lerobot_check/requirements.txt "
           "(make does this)")


class LeRobotMissingError(ImportError):
    """LeRobot's package directory is not there."""


def use_lerobot() -> None:
    """Put LeRobot and the torchvision stand-in on ``sys.path`` (once); LeRobotMissingError with the
    install command when LeRobot is not installed beside the venv."""
    if not (LEROBOT_SITE / "lerobot").is_dir():
        raise LeRobotMissingError(f"LeRobot is not installed in {LEROBOT_SITE}: {INSTALL}")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # nothing is downloaded at run time
    for path in (str(LEROBOT_SITE), str(SHIM)):
        if path not in sys.path:  # after the venv: its versions of the packages both hold win
            sys.path.append(path)
