"""Stand-in for torchvision when LeRobot's dataset class reads an export in the tests.

The only torchvision wheels for torch 2.13.0 are CUDA builds whose compiled operators need CUDA
torch libraries; with the CPU torch they fail at import. LeRobot's dataset module imports
``torchvision.transforms`` only for image augmentation, which the tests do not use, and decodes
video through torchvision or torchcodec, which the tests replace by PyAV."""

__version__ = "0.28.0"

from . import transforms  # noqa: F401,E402
