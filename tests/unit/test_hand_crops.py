"""The detector's second stage: per-hand crops placed from the first stage's peaks through all
views' geometry, the crop's pixel maps both ways (mirrored for the left hand), the crop network's
peaks replacing the first stage's in full-image pixels, and its training crops."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from perception.augment import NO_AUGMENT
from perception.hand_stage import crop_sample
from perception.labels import keypoint_names
from services.recon import hand_crops
from services.recon.detector import CameraModel
from services.recon.learned_detector import LearnedDetector, UNet, View, peaks
from services.recon.triangulation import project
from services.world.model import camera_specs
from shared.geometry import projection

W, H = 256, 192


@pytest.fixture(autouse=True)
def denormals_restored():
    yield
    torch.set_flush_denormal(False)


def rig() -> np.ndarray:
    return np.stack([projection(c.K, c.world_T_cam) for c in camera_specs(W, H)])


def two_hands(rng: np.random.Generator) -> np.ndarray:
    """(42,3): two hands of 21 points within 6 cm of centres 20 cm apart over the table."""
    centres = np.array([[-0.1, 0.0, 0.15], [0.1, 0.02, 0.12]])
    return np.concatenate([c + rng.uniform(-0.06, 0.06, (21, 3)) for c in centres])


def test_crop_matrix_maps_the_box_onto_the_crop_and_back():
    for mirror in (False, True):
        M = hand_crops.crop_matrix(np.array([50.0, 40.0]), 16.0, 32, mirror)
        box = np.array([[50.0, 40.0], [66.0, 40.0], [50.0, 24.0]])
        crop = box @ M[:, :2].T + M[:, 2]
        assert np.allclose(crop[0], 15.5)
        assert np.allclose(crop[1], [15.5 - 16 if mirror else 15.5 + 16, 15.5])  # mirrored: right goes left
        assert np.allclose(crop[2], [15.5, -0.5])
        assert np.allclose(hand_crops.to_image(crop, M), box)


def test_focal_and_boxes_follow_the_hands_depth():
    P = rig()
    f = np.array([hand_crops.focal_px(p) for p in P])
    assert np.allclose(f, camera_specs(W, H)[0].K[0, 0])
    centre = np.array([[0.0, 0.0, 0.1], [0.0, 0.0, 50.0]])
    pix, depth = project(P, centre)
    box, half, ok = hand_crops.hand_boxes(P, centre, np.array([True, False]), f)
    assert ok[:, 0].all() and not ok[:, 1].any()  # a hand not found gets no box
    assert np.allclose(box[:, 0], pix[:, 0])
    dist = np.linalg.norm(centre[0] - np.array([c.world_T_cam[:3, 3] for c in camera_specs(W, H)]), axis=1)
    assert np.all(half[:, 0] > f * hand_crops.HALF_SIZE_M / dist - 1e-9)  # depth along the axis <= distance
    assert np.all(half[:, 0] < 1.5 * f * hand_crops.HALF_SIZE_M / dist)


def test_hand_centres_survive_peaks_on_the_other_hand_and_need_two_views():
    rng = np.random.default_rng(3)
    P = rig()
    pts = two_hands(rng)
    uv, _ = project(P, pts)
    uv = uv + rng.normal(0, 1.0, uv.shape)
    wrong = rng.random((len(P), 21)) < 0.3  # a third of the left hand's peaks on the right hand
    uv[:, :21][wrong] = uv[:, 21:][wrong]
    conf = np.ones(uv.shape[:2])
    slices = [slice(0, 21), slice(21, 42)]
    centres, found = hand_crops.hand_centres(P, uv, conf, slices)
    assert found.all()
    for h, sl in enumerate(slices):
        assert np.linalg.norm(centres[h] - pts[sl].mean(axis=0)) < 0.04
    conf[1:, 21:] = 0.0  # the right hand seen by one camera only
    _, found = hand_crops.hand_centres(P, uv, conf, slices)
    assert found.tolist() == [True, False]


def test_hand_centres_are_not_dragged_toward_the_other_hand():
    """Peaks of one hand's channel that every view puts on the other hand triangulate there; they
    must not pull the crop's centre (the second stage follows its crop's centre)."""
    rng = np.random.default_rng(4)
    P = rig()
    pts = two_hands(rng)
    uv, _ = project(P, pts)
    uv = uv + rng.normal(0, 1.0, uv.shape)
    wrong = rng.permutation(21)[:8]  # 8 of the right hand's keypoints found on the left hand in every view
    uv[:, 21 + wrong] = uv[:, wrong]
    conf = np.ones(uv.shape[:2])
    slices = [slice(0, 21), slice(21, 42)]
    centres, found = hand_crops.hand_centres(P, uv, conf, slices)
    per_view, _ = hand_crops._median_centres(P, uv, conf, slices, 0.3)
    truth = np.median(pts[21:], axis=0)
    assert found.all()
    assert np.linalg.norm(centres[1] - truth) < 0.015
    assert np.linalg.norm(centres[1] - truth) < 0.5 * np.linalg.norm(per_view[1] - truth)


def second_stage(tmp_path, half_px_peak: float) -> LearnedDetector:
    names = keypoint_names("assembly")
    torch.save(UNet(len(names)).state_dict(), tmp_path / "weights.pt")
    (tmp_path / "meta.json").write_text(json.dumps({"task": "assembly", "keypoints": names, "input_size": [32, 24]}))
    torch.save(UNet(21).state_dict(), tmp_path / "hands.pt")
    (tmp_path / "hands.json").write_text(json.dumps({"input_size": 32}))
    det = LearnedDetector(tmp_path, runtime="torch")
    ys, xs = np.mgrid[:32, :32]
    target = np.exp(-((xs - 15.5 - half_px_peak) ** 2 + (ys - 15.5) ** 2) / (2 * 1.5**2)).astype(np.float32)
    det._run_hand = lambda batch: np.broadcast_to(target, (len(batch), 21, 32, 32)).copy()
    return det


def test_the_second_stage_replaces_each_hands_peaks_around_its_centre(tmp_path):
    rng = np.random.default_rng(4)
    P = rig()
    pts = two_hands(rng)
    truth, _ = project(P, pts)
    det = second_stage(tmp_path, half_px_peak=4.0)  # every crop's peaks 4 crop pixels right of its centre
    views = [View(f"cam{i}", CameraModel(P[i], W, H, (0, 0, W, H)), np.zeros((H, W, 3), np.uint8))
             for i in range(len(P))]
    first = np.zeros((len(P), len(det.names), 2))
    first[:, :42] = truth
    conf = np.ones(first.shape[:2])
    uv = first.copy()
    det._refine_hands(views, [v.image for v in views], uv, conf)
    centres, _ = hand_crops.hand_centres(P, first, np.ones_like(conf), det.hand_slices)
    f = np.array([hand_crops.focal_px(p) for p in P])
    box, half, _ = hand_crops.hand_boxes(P, centres, np.ones(2, bool), f)
    step = 4.0 * 2 * half / 32  # crop pixels -> image pixels
    assert np.allclose(uv[:, :21], (box[:, 0] - np.c_[step[:, 0], np.zeros(len(P))])[:, None], atol=1e-3)  # mirrored
    assert np.allclose(uv[:, 21:42], (box[:, 1] + np.c_[step[:, 1], np.zeros(len(P))])[:, None], atol=1e-3)
    assert np.allclose(uv[:, 42:], first[:, 42:])  # objects keep the first stage's peaks
    assert np.all(conf[:, :42] > 0.9)


def test_the_second_stage_leaves_views_without_geometry_or_windows_alone(tmp_path):
    det = second_stage(tmp_path, 0.0)
    views = [View(f"cam{i}", CameraModel(np.zeros((3, 4)), W, H, (0, 0, 64, 48)), np.zeros((48, 64, 3), np.uint8))
             for i in range(3)]
    uv = np.random.default_rng(5).uniform(0, 40, (3, len(det.names), 2))
    conf = np.ones(uv.shape[:2])
    before = uv.copy()
    det._refine_hands(views, [v.image for v in views], uv, conf)
    assert np.array_equal(uv, before) and (conf == 1).all()
    P = rig()
    pts = two_hands(np.random.default_rng(6))
    pix, _ = project(P, pts)
    corner = (200, 150, 56, 42)  # every view's window in the image's corner, far from both hands
    assert (pix[..., 0].max() < corner[0] - 20) and (pix[..., 1].max() < corner[1] - 20)
    views = [View(f"cam{i}", CameraModel(P[i], W, H, corner), np.zeros((42, 56, 3), np.uint8)) for i in range(len(P))]
    uv = np.zeros((len(P), len(det.names), 2))
    uv[:, :42] = pix
    conf = np.ones(uv.shape[:2])
    det._refine_hands(views, [v.image for v in views], uv, conf)
    assert (conf[:, :42] == 0).all()  # the views do not see the hands
    assert (conf[:, 42:] == 1).all() and np.isfinite(uv).all()


def test_training_crops_hold_their_hands_keypoints_mirrored_for_the_left():
    rng = np.random.default_rng(6)
    img = np.zeros((120, 160, 3), np.uint8)
    uv = rng.uniform(60, 90, (21, 2))
    labelled = np.ones(21, bool)
    labelled[3] = False
    for mirror in (False, True):
        x, y = crop_sample(img, uv, labelled, mirror, 32, NO_AUGMENT, np.random.default_rng(7))
        assert x.shape == (3, 32, 32) and y.shape == (21, 32, 32)
        assert y[3].max() == 0.0  # unlabelled: no target
        got, _ = peaks(y)
        order = np.argsort(got[labelled, 0])
        expect = np.argsort(-uv[labelled, 0] if mirror else uv[labelled, 0])
        assert np.array_equal(order[[0, -1]], expect[[0, -1]])  # leftmost and rightmost swap when mirrored
