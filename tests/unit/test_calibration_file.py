"""The rig calibration file round-trips and refuses what does not fit the rig."""

import json

import numpy as np
import pytest

from shared import calibration as C


def _rig() -> C.RigCalibration:
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, 3] = [0.1, 0.2, 0.8]
    return C.RigCalibration([C.CameraCalibration("cam0", 640, 480, K, np.zeros(5), pose, 0.2)])


def test_round_trip_keeps_every_field(tmp_path):
    path = tmp_path / "rig.json"
    C.save(_rig(), path)
    back = C.load(path)
    cam = back.camera("cam0")
    assert (cam.width, cam.height) == (640, 480)
    np.testing.assert_array_equal(cam.world_T_cam, _rig().cameras[0].world_T_cam)
    assert cam.rms_px == 0.2 and back.date


def test_projection_maps_a_world_point_to_its_pixel():
    cam = _rig().cameras[0]
    p = cam.projection() @ np.array([0.1, 0.2, 1.8, 1.0])  # 1 m in front of the camera, on its axis
    assert np.allclose(p[:2] / p[2], [320, 240])


def test_mismatched_rig_is_refused_with_the_camera_named():
    rig = _rig()
    with pytest.raises(C.CalibrationError, match="cam1"):
        rig.check_rig({"cam0": (640, 480), "cam1": (640, 480)})
    with pytest.raises(C.CalibrationError, match="320x240"):
        rig.check_rig({"cam0": (320, 240)})


def test_malformed_files_say_what_is_wrong(tmp_path):
    data = C.to_json(_rig())
    data["cameras"][0]["K"] = [[1, 2], [3, 4]]
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(C.CalibrationError, match="K: shape"):
        C.load(path)
    with pytest.raises(C.CalibrationError, match="no such calibration"):
        C.load(tmp_path / "missing.json")
