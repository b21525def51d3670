"""camhub's sources as a process seen through Zenoh: intrinsics from a calibration file, windows
that follow a published scene, a mismatched calibration refused, a camera folder that disappears."""

from __future__ import annotations

import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

from services.world.model import camera_specs
from shared import calibration, msgs
from tests.conftest import ROOT, ServiceProcess, query_json, wait_for, write_deployment

pytestmark = pytest.mark.slow


def collect(session, key: str, msgtype: str) -> tuple[list, object]:
    out: list = []
    sub = session.declare_subscriber(key, lambda s: out.append(msgs.deserialize(s.payload.to_bytes(), msgtype)))
    return out, sub


def true_calibration(width: int, height: int, names: list[str] | None = None, fx_scale: float = 1.0):
    cams = []
    for c in camera_specs(width, height):
        if names is None or c.name in names:
            K = c.K.copy()
            K[0, 0] *= fx_scale
            cams.append(calibration.CameraCalibration(c.name, width, height, K, np.zeros(5), c.world_T_cam, 0.1))
    return calibration.RigCalibration(cams, date="2026-11-27T00:00:00+00:00")


def world_params(tmp_path) -> dict:
    run = tmp_path / "run"
    return {"glove_ports": [str(run / "glove-left"), str(run / "glove-right")], "robot_port": str(run / "board")}


def test_sim_rig_publishes_the_calibration_files_intrinsics_and_windows_that_follow_the_hands(router, tmp_path):
    endpoint, session = router
    calibration.save(true_calibration(320, 240, fx_scale=1.01), tmp_path / "rig.json")
    dep = write_deployment(tmp_path / "d.toml", endpoint, {
        "world": {"sim": world_params(tmp_path)},
        "camhub": {"main": {"rate_hz": 5.0, "calibration": str(tmp_path / "rig.json"), "roi_reacquire_every": 0}}},
        clock="sim")
    world = ServiceProcess("world", dep, "sim", tmp_path / "world.log")
    cam = ServiceProcess("camhub", dep, "main", tmp_path / "camhub.log")
    try:
        infos, _a = collect(session, "xm/camhub/cam0/info", "sensor_msgs/msg/CameraInfo")
        images, _b = collect(session, "xm/camhub/cam0/image", "sensor_msgs/msg/CompressedImage")
        assert wait_for(lambda: infos, 60), cam.output()
        spec = camera_specs(320, 240)[0]
        assert np.asarray(infos[0].k).reshape(3, 3)[0, 0] == pytest.approx(1.01 * spec.K[0, 0])
        assert (infos[0].roi.width, infos[0].roi.height) == (320, 240), "no scene yet: full frame"
        health = query_json(session, "xm/camhub/main/@health")[0]
        assert health["intrinsics"] == f"calibration {tmp_path / 'rig.json'}" and not health["tracking"]
        hands = np.array([0.05, 0.0, 0.1]) + np.random.default_rng(0).uniform(-0.03, 0.03, (42, 3))

        def windowed() -> bool:  # a scene stamped at the rig's latest trigger, as recon would publish
            stamp = msgs.stamp_seconds(infos[-1].header.stamp)
            session.put("xm/recon/main/scene", msgs.serialize(msgs.make(
                "xm_msgs/msg/Scene", header=msgs.header(stamp, "world"), hand_names=["left", "right"],
                hand_keypoints=hands.astype(np.float32).ravel(), hand_mask=np.ones(42, np.uint8),
                object_names=[], object_keypoints=np.zeros(0, np.float32), object_mask=np.zeros(0, np.uint8),
                tactile_regions=[], tactile=np.zeros(0, np.float32), tactile_mask=np.zeros(0, np.uint8)),
                "xm_msgs/msg/Scene"))
            health = query_json(session, "xm/camhub/main/@health")
            return infos[-1].roi.width < 320 and health and health[0]["tracking"]
        assert wait_for(windowed, 30, period=0.3), cam.output()
        info = infos[-1]
        image = next(m for m in reversed(images) if m.header.stamp == info.header.stamp)
        rgb = cv2.imdecode(np.frombuffer(bytes(image.data), np.uint8), cv2.IMREAD_COLOR)
        assert rgb.shape[:2] == (info.roi.height, info.roi.width), "the image is the window CameraInfo names"
        uv = spec.K @ (np.linalg.inv(spec.world_T_cam) @ [*hands.mean(axis=0), 1.0])[:3]
        u, v = uv[:2] / uv[2]
        assert info.roi.x_offset < u < info.roi.x_offset + info.roi.width
        assert info.roi.y_offset < v < info.roi.y_offset + info.roi.height
    finally:
        cam.stop()
        world.stop()


@pytest.mark.parametrize("case", ["missing_camera", "resolution"])
def test_a_calibration_that_does_not_match_the_rig_is_refused_by_name(router, tmp_path, case):
    if case == "missing_camera":
        rig = true_calibration(320, 240, names=[f"cam{i}" for i in range(6)])
        expect = "no calibration for camera(s) cam6"
    else:
        rig = true_calibration(640, 480)
        expect = "calibrated at 640x480 but the rig runs it at 320x240"
    calibration.save(rig, tmp_path / "rig.json")
    dep = write_deployment(tmp_path / "d.toml", router[0], {
        "camhub": {"main": {"source": "files", "calibration": str(tmp_path / "rig.json"),
                            "files": [str(tmp_path / f"cam{i}") for i in range(7)]}}})
    out = subprocess.run([sys.executable, "-m", "services.camhub", "--deployment", str(dep), "--instance", "main"],
                         cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out.stdout + out.stderr
    assert expect in out.stderr and str(tmp_path / "rig.json") in out.stderr


def test_a_camera_folder_that_disappears_leaves_the_others_publishing_and_comes_back(router, tmp_path):
    endpoint, session = router
    w, h = 64, 48
    calibration.save(true_calibration(w, h), tmp_path / "rig.json")
    folders = []
    for i in range(7):
        folder = tmp_path / f"cam{i}"
        folder.mkdir()
        for k in range(3):
            cv2.imwrite(str(folder / f"{k}.png"), np.full((h, w, 3), 20 * i + k, np.uint8))
        folders.append(str(folder))
    dep = write_deployment(tmp_path / "d.toml", endpoint, {
        "camhub": {"main": {"source": "files", "calibration": str(tmp_path / "rig.json"), "files": folders,
                            "width": w, "height": h, "rate_hz": 10.0}}})
    cam = ServiceProcess("camhub", dep, "main", tmp_path / "camhub.log")
    try:
        infos, _a = collect(session, "xm/camhub/*/info", "sensor_msgs/msg/CameraInfo")

        def cameras() -> dict:
            got = query_json(session, "xm/camhub/main/@health")
            return got[0]["cameras"] if got else {}
        assert wait_for(lambda: {i.header.frame_id for i in infos} == {f"cam{i}" for i in range(7)}, 30), cam.output()
        shutil.move(folders[3], tmp_path / "unplugged")
        assert wait_for(lambda: cameras().get("cam3", {}).get("status") == "missing", 20), cam.output()
        n = len(infos)
        assert wait_for(lambda: len({i.header.frame_id for i in infos[n:]}) == 6, 10), "the other six keep publishing"
        assert "cam3" not in {i.header.frame_id for i in infos[n + 6:]}
        health = query_json(session, "xm/camhub/main/@health")[0]
        assert health["status"] == "degraded" and "cam3" in health["message"]
        assert health["cameras"]["cam3"]["gaps"] >= 1 and health["errors"].get("camera_missing", 0) >= 1
        shutil.move(tmp_path / "unplugged", folders[3])
        assert wait_for(lambda: cameras().get("cam3", {}).get("reopened") == 1, 20), cameras()
        n = len(infos)
        assert wait_for(lambda: "cam3" in {i.header.frame_id for i in infos[n:]}, 10)
    finally:
        assert cam.stop() in (0, -15), cam.output()
