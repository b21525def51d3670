"""Stand-in for torchvision where LeRobot runs beside the venv (interop/lerobot_site.py: Table 7.1
row (8), and the tests that read an export with LeRobot's dataset class).

The only torchvision wheels for torch 2.13.0 are CUDA builds whose compiled operators need CUDA
torch libraries; with the CPU torch they fail at import. LeRobot imports torchvision at module
level for image augmentation, image processor steps and its policies' image encoders, none of which
state-only use runs (no camera features reach a policy), and decodes video through torchvision or
torchcodec, which the tests replace by PyAV."""

__version__ = "0.28.0"

from . import transforms  # noqa: F401,E402
