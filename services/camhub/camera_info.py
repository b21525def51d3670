"""Pure conversions for camera messages and the rig's camera geometry."""

from __future__ import annotations

import cv2
import numpy as np

from services.camhub.roi import CameraGeometry, Roi
from shared import msgs
from shared.calibration import RigCalibration
from shared.geometry import projection


def encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def from_calibration(rig: RigCalibration, names: list[str]) -> list[CameraGeometry]:
    """The running cameras' geometry, in the rig's order (``check_rig`` has matched names and sizes)."""
    out = []
    for name in names:
        c = rig.camera(name)
        out.append(CameraGeometry(name, c.width, c.height, c.K, c.dist, c.world_T_cam))
    return out


def camera_info(header: object, cam: CameraGeometry, roi: Roi) -> object:
    """CameraInfo of one frame: the full image's calibration (width, height, K, D, P = K [R|t] with
    [R|t] = cam_T_world) and the window this frame's image shows in ``roi``."""
    return msgs.make(
        "sensor_msgs/msg/CameraInfo", header=header, height=cam.height, width=cam.width,
        distortion_model="plumb_bob", d=np.asarray(cam.dist, float), k=np.asarray(cam.K, float).ravel(),
        r=np.eye(3).ravel(), p=projection(cam.K, cam.world_T_cam).ravel().astype(float), binning_x=0, binning_y=0,
        roi=msgs.make("sensor_msgs/msg/RegionOfInterest", x_offset=roi.x_offset, y_offset=roi.y_offset,
                      height=roi.height, width=roi.width, do_rectify=False))

