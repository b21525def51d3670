"""camhub's device rig on file sources: frame sets, windows, a camera that disappears and returns
(services/camhub/driver.py, services/camhub/reopen.py)."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from services.camhub.driver import DeviceRig, FileSource, RigError, SizeMismatchError
from services.camhub.reopen import CameraState
from services.camhub.roi import Roi

W, H = 64, 48


def frame(cam: int, index: int) -> np.ndarray:
    """BGR image whose pixels encode (camera, frame index)."""
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = 10 * cam
    img[..., 1] = index
    return img


def image_folders(tmp_path, cams: int = 3, frames: int = 5) -> list[str]:
    out = []
    for c in range(cams):
        folder = tmp_path / f"cam{c}"
        folder.mkdir()
        for i in range(frames):
            cv2.imwrite(str(folder / f"{i:04d}.png"), frame(c, i))
        out.append(str(folder))
    return out


def rig_on(paths: list[str], loop: bool = True) -> DeviceRig:
    names = [f"cam{i}" for i in range(len(paths))]
    return DeviceRig(names, [FileSource(p, W, H, loop) for p in paths], W, H)


def test_backoff_doubles_to_a_ceiling_and_counts_losses_and_reopens():
    s = CameraState("cam0", first_retry_s=0.5, max_retry_s=2.0)
    s.opened()
    assert s.open and not s.due(0.0)
    s.failed(10.0, "gone")
    assert (s.losses, s.error, s.open) == (1, "gone", False)
    assert not s.due(10.4) and s.due(10.5)
    s.failed(10.5, "still gone")
    assert not s.due(11.4) and s.due(11.5)
    s.failed(11.5, "still gone")
    s.failed(13.5, "still gone")
    assert s.retry_at == pytest.approx(15.5), "delay capped at max_retry_s"
    assert s.losses == 1, "failed reopen attempts are not new losses"
    s.opened()
    assert (s.reopened, s.report()["status"]) == (1, "ok")
    s.failed(20.0, "gone again")
    assert s.retry_at == pytest.approx(20.5), "back-off starts over after a success"


def test_frame_sets_share_one_stamp_and_index_and_windows_are_cropped(tmp_path):
    rig = rig_on(image_folders(tmp_path))
    assert rig.open_all(0.0) == []
    windows = {"cam1": Roi(8, 4, 16, 10)}
    for i in range(7):  # past the end: the recording loops
        fs = rig.trigger(windows, now=float(i))
        assert fs.stamp == float(i) and not fs.missing
        assert [f.name for f in fs.frames] == ["cam0", "cam1", "cam2"]
        for c, f in enumerate(fs.frames):
            assert f.image[0, 0, 2] == 10 * c and f.image[0, 0, 1] == i % 5, "RGB: index in green, camera in blue"
        assert fs.frames[1].image.shape == (10, 16, 3) and fs.frames[1].roi == Roi(8, 4, 16, 10)
        assert fs.frames[0].image.shape == (H, W, 3) and fs.frames[0].roi == Roi(0, 0, W, H)


def test_a_camera_that_disappears_is_reported_the_others_keep_delivering_and_it_is_reopened(tmp_path):
    paths = image_folders(tmp_path)
    rig = rig_on(paths)
    rig.open_all(0.0)
    rig.trigger({}, 0.0)
    shutil.move(paths[1], tmp_path / "unplugged")
    fs = rig.trigger({}, 1.0)
    assert fs.missing == ["cam1"] and [f.name for f in fs.frames] == ["cam0", "cam2"]
    health = rig.health()["cam1"]
    assert health["status"] == "missing" and "unreadable" in health["error"] and health["gaps"] == 1
    fs = rig.trigger({}, 1.2)  # before the back-off: not retried, still missing
    assert fs.missing == ["cam1"]
    shutil.move(tmp_path / "unplugged", paths[1])
    fs = rig.trigger({}, 1.6)
    assert not fs.missing
    assert fs.frames[1].image[0, 0, 1] == fs.frames[0].image[0, 0, 1], "the returning camera rejoins the same index"
    assert rig.health()["cam1"] | {"error": ""} == {"status": "ok", "frames": 2, "gaps": 2, "losses": 1,
                                                     "reopened": 1, "error": ""}


def test_a_missing_path_at_start_is_retried_and_all_missing_raises(tmp_path):
    paths = image_folders(tmp_path, cams=2)
    rig = rig_on([paths[0], str(tmp_path / "nowhere")])
    failures = rig.open_all(0.0)
    assert len(failures) == 1 and "no such file" in str(failures[0])
    assert rig.trigger({}, 0.0).missing == ["cam1"]
    lost = rig_on([str(tmp_path / "a"), str(tmp_path / "b")])
    lost.open_all(0.0)
    with pytest.raises(RigError, match="cam0: .*no such file"):
        lost.trigger({}, 1.0)


def test_a_source_at_another_resolution_is_a_size_mismatch(tmp_path):
    folder = tmp_path / "big"
    folder.mkdir()
    cv2.imwrite(str(folder / "0.png"), np.zeros((H * 2, W * 2, 3), np.uint8))
    failures = rig_on([str(folder)]).open_all(0.0)
    assert len(failures) == 1 and isinstance(failures[0], SizeMismatchError)
    assert f"{2 * W}x{2 * H}" in str(failures[0]) and f"{W}x{H}" in str(failures[0])


def test_video_files_play_in_order_and_end_without_loop(tmp_path):
    path = tmp_path / "cam0.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    assert writer.isOpened()
    for i in range(4):
        writer.write(frame(0, 40 * i))
    writer.release()
    rig = rig_on([str(path)], loop=False)
    assert rig.open_all(0.0) == []
    greens = [int(rig.trigger({}, float(i)).frames[0].image[H // 2, W // 2, 1]) for i in range(4)]
    assert np.allclose(greens, [0, 40, 80, 120], atol=6), greens  # JPEG in the AVI: close, not exact
    with pytest.raises(RigError, match="end of recording"):
        rig.trigger({}, 5.0)


def test_a_video_device_that_does_not_exist_is_missing_not_fatal(tmp_path):
    from services.camhub.driver import V4L2Source

    rig = DeviceRig(["cam0", "cam1"], [V4L2Source(str(tmp_path / "video99"), W, H, 10.0),
                                       FileSource(image_folders(tmp_path, cams=1)[0], W, H)], W, H)
    failures = rig.open_all(0.0)
    assert len(failures) == 1 and "cannot open video device" in str(failures[0])
    fs = rig.trigger({}, 0.0)
    assert fs.missing == ["cam0"] and [f.name for f in fs.frames] == ["cam1"]
