"""The per-camera readout windows that follow the hands (services/camhub/roi.py)."""

from __future__ import annotations

import numpy as np
import pytest

from services.camhub import roi
from services.world.model import camera_specs


def geometry(width: int = 640, height: int = 480) -> list[roi.CameraGeometry]:
    return [roi.CameraGeometry(c.name, width, height, c.K, np.zeros(5), c.world_T_cam)
            for c in camera_specs(width, height)]


@pytest.mark.parametrize("seed", range(20))
def test_window_covers_the_box_is_even_aligned_and_inside_the_image(seed):
    rng = np.random.default_rng(seed)
    w, h = 640, 480
    lo = rng.uniform([-50, -50], [w, h])
    hi = lo + rng.uniform(0, 300, 2)
    r = roi.fit_window(lo, hi, w, h, min_px=64)
    assert r.x_offset % 2 == 0 and r.y_offset % 2 == 0 and r.width % 2 == 0 and r.height % 2 == 0
    assert 0 <= r.x_offset and r.x_offset + r.width <= w and 0 <= r.y_offset and r.y_offset + r.height <= h
    assert r.width >= 64 and r.height >= 64
    keep_lo = np.clip(np.floor(lo), 0, [w - 1, h - 1])
    keep_hi = np.clip(np.ceil(hi), 0, [w - 1, h - 1])
    if (hi >= 0).all() and (lo <= [w - 1, h - 1]).all():
        assert r.x_offset <= keep_lo[0] and keep_hi[0] < r.x_offset + r.width
        assert r.y_offset <= keep_lo[1] and keep_hi[1] < r.y_offset + r.height


def test_windows_hold_the_projected_hands_with_margin_and_are_smaller_than_the_frame():
    cams = geometry()
    hand = np.array([0.05, -0.05, 0.1]) + np.random.default_rng(0).uniform(-0.04, 0.04, (21, 3))
    params = roi.RoiParams(margin_m=0.05, reacquire_every=0)
    windows, tracked = roi.rig_windows(cams, hand, scene_age_s=0.1, trigger=1, params=params)
    assert tracked
    for cam in cams:
        r = windows[cam.name]
        assert r.width * r.height < 0.5 * cam.width * cam.height, f"{cam.name}: {r}"
        uv, depth = roi.project(hand, cam.K, cam.dist, cam.world_T_cam)
        pad = cam.K[0, 0] * 0.05 / depth
        assert np.all(uv[:, 0] - pad >= r.x_offset - 1) and np.all(uv[:, 0] + pad <= r.x_offset + r.width + 1)
        assert np.all(uv[:, 1] - pad >= r.y_offset - 1) and np.all(uv[:, 1] + pad <= r.y_offset + r.height + 1)


def test_projection_matches_the_pinhole_model_and_depth():
    cam = geometry()[0]
    p = np.array([[0.03, 0.0, 0.02]])
    uv, depth = roi.project(p, cam.K, cam.dist, cam.world_T_cam)
    x = np.linalg.inv(cam.world_T_cam) @ [*p[0], 1.0]
    assert depth[0] == pytest.approx(x[2])
    assert uv[0] == pytest.approx((cam.K @ x[:3] / x[2])[:2])


@pytest.mark.parametrize("case", ["no_scene", "stale", "too_few", "reacquire", "behind", "outside"])
def test_full_frame_when_tracking_is_lost(case):
    cams = geometry()
    params = roi.RoiParams(reacquire_every=10)
    hand = np.full((21, 3), [0.0, 0.0, 0.1])
    points, age, trigger = hand, 0.1, 3
    if case == "no_scene":
        points = None
    elif case == "stale":
        age = 2.0
    elif case == "too_few":
        points = hand[:2]
    elif case == "reacquire":
        trigger = 20
    elif case == "behind":
        points = np.full((21, 3), [0.0, 0.0, 5.0])  # above every camera
    elif case == "outside":
        points = np.full((21, 3), [3.0, 3.0, 0.0])  # far off the table
    windows, tracked = roi.rig_windows(cams, points, age, trigger, params)
    assert all(w == roi.full_frame(640, 480) for w in windows.values())
    assert tracked == (case in ("reacquire", "behind", "outside"))


def test_tracked_points_keeps_the_observed_finite_keypoints_and_rejects_a_bad_mask():
    pts = np.arange(42 * 3, dtype=float).reshape(42, 3)
    pts[5] = np.nan
    mask = np.ones(42, np.uint8)
    mask[:21] = 0
    assert len(roi.tracked_points(pts.ravel(), mask)) == 21
    mask[5] = 1
    assert len(roi.tracked_points(pts.ravel(), mask)) == 21  # NaN point dropped though marked observed
    assert len(roi.tracked_points(pts.ravel(), [])) == 41, "empty mask: every finite keypoint"
    with pytest.raises(ValueError, match="hand_mask"):
        roi.tracked_points(pts.ravel(), np.ones(5))


def test_crop_and_mapping_back_to_the_full_image():
    image = np.arange(480 * 640).reshape(480, 640)
    r = roi.Roi(100, 50, 64, 32)
    sub = roi.crop(image, r)
    assert sub.shape == (32, 64)
    v, u = 10, 20
    full_u, full_v = roi.to_full_image(np.array([[u, v]]), r)[0]
    assert image[int(full_v), int(full_u)] == sub[v, u]


def test_a_missing_hand_brings_full_frames_every_second_trigger():
    cams = geometry()
    hand = np.array([0.05, -0.05, 0.1]) + np.random.default_rng(1).uniform(-0.04, 0.04, (21, 3))
    params = roi.RoiParams(reacquire_every=10, reacquire_lost_every=2)
    mask = np.ones(42, np.uint8)
    assert not roi.missing_hand(mask, 2) and not roi.missing_hand([], 2)
    mask[21:] = 0
    mask[21:23] = 1  # two keypoints of the right hand: too few to track it
    assert roi.missing_hand(mask, 2)
    with pytest.raises(ValueError, match="hand_mask"):
        roi.missing_hand(np.ones(41), 2)
    full = roi.full_frame(640, 480)
    for trigger in range(1, 7):
        both, _ = roi.rig_windows(cams, hand, 0.1, trigger, params, hand_missing=False)
        one, _ = roi.rig_windows(cams, hand, 0.1, trigger, params, hand_missing=True)
        assert all(w != full for w in both.values())
        assert all((w == full) == (trigger % 2 == 0) for w in one.values())
