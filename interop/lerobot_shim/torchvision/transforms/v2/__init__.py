"""The base class LeRobot's image augmentations derive from at import (never instantiated here)."""

import torch

from . import functional  # noqa: F401


class Transform(torch.nn.Module):
    pass
