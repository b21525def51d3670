"""From detections to the rig calibration file: initial guess, bundle adjustment, registration.

The world frame: frame set ``registration_frame`` shows the board lying on the table at a known
place (``world_T_board``, from the deployment's ``[calibration] registration``). Its corners,
triangulated by the calibrated rig, are fitted to their known world positions (calibration/register.py);
when fewer than two cameras saw it, its bundle-adjusted pose ties the rig to the world instead:
world_T_rig = world_T_board @ inv(rig_T_board).
"""

from __future__ import annotations

import datetime as _dt
import time
from dataclasses import dataclass

import numpy as np

from calibration import register
from calibration.bundle import BundleResult, bundle_adjust
from calibration.detect import Detection, Detections
from calibration.init import CaptureUnusableError, initial_guess
from shared.calibration import CameraCalibration, RigCalibration
from shared.charuco import BoardSpec


@dataclass
class Calibrated:
    rig: RigCalibration
    bundle: BundleResult
    seconds: dict[str, float]


def inlier_views(result: BundleResult, frame: int) -> list[Detection]:
    """One frame set's corners that the bundle adjustment kept, per camera."""
    obs = result.obs
    sel = result.inlier & (obs.frame == obs.frames.index(frame))
    return [Detection(int(c), frame, obs.ids[sel & (obs.cam == c)], obs.uv[sel & (obs.cam == c)])
            for c in np.unique(obs.cam[sel])]


def calibrate(det: Detections, board: BoardSpec, world_T_board: np.ndarray, registration_frame: int = 0,
              model: str = "full") -> Calibrated:
    """``model``: the camera model (``bundle.MODELS``): "full" OpenCV intrinsics or "centred"."""
    t0 = time.perf_counter()
    init = initial_guess(det, board, model)
    t1 = time.perf_counter()
    if registration_frame not in init.rig_T_board:
        raise CaptureUnusableError(
            f"no camera saw the registration board (frame set {registration_frame}): lay the board flat on the "
            "table where the deployment's [calibration] registration says, in view of the cameras, and capture "
            "it first")
    result = bundle_adjust(det, board, init, model=model)
    t2 = time.perf_counter()
    world_T_rig = register.world_T_rig(inlier_views(result, registration_frame), result.K, result.dist,
                                       result.cam_T_rig, board.corners(), world_T_board)
    if world_T_rig is None:
        world_T_rig = world_T_board @ np.linalg.inv(result.rig_T_board[registration_frame])
    cams = [CameraCalibration(name, *det.image_sizes[c], result.K[c], result.dist[c],
                              world_T_rig @ np.linalg.inv(result.cam_T_rig[c]), result.rms_px[c])
            for c, name in enumerate(det.names)]
    rig = RigCalibration(cams, np.linalg.inv(world_T_board),
                         _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"), board.to_dict())
    return Calibrated(rig, result, {"init_s": t1 - t0, "bundle_s": t2 - t1})
