"""Multi-camera calibration with a ChArUco board (thesis 5.5): offline code behind ``xm calibrate``.

detect (ChArUco corners per image, degenerate views skipped) -> init (monocular intrinsics,
extrinsics chained over the co-visibility graph) -> bundle (global robust bundle adjustment) ->
the rig calibration file of ``shared/calibration.py`` and a report.
"""

import os

# The simulated captures render offscreen: MuJoCo picks its GL platform when first imported, and
# this package imports the world model (hence MuJoCo) before the renderer would set it.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("LP_NUM_THREADS", "1")
