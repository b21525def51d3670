"""Stand-in for torchvision when LeRobot's dataset class reads an export in the tests.

The only torchvision wheels for torch 2.13.0 are CUDA builds whose compiled operators need CUDA
torch libraries; with the CPU torch they fail at import. LeRobot imports torchvision at module
level for image augmentation, image processor steps and its policies' image encoders, none of which
the tests run (no camera features reach a policy), and decodes video through torchvision or
torchcodec, which the tests replace by PyAV."""

__version__ = "0.28.0"

from . import transforms  # noqa: F401,E402
