"""The detector's object stage: per-object crops placed from the first stage's peaks through all
views' geometry (exchanged keypoints of one object do not move them), the crop network's peaks of
that object's keypoints replacing the first stage's in full-image pixels, weights for other
keypoints refused, and its training crops (not mirrored)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from perception.augment import NO_AUGMENT
from perception.labels import keypoint_names
from perception.object_stage import crop_sample, object_table, pixels_per_metre
from services.recon import hand_crops, object_crops
from services.recon.detector import CameraModel
from services.recon.learned_detector import LearnedDetector, UNet, View, peaks
from services.recon.objects import object_models
from services.recon.triangulation import project
from services.world.model import camera_specs
from shared.geometry import projection

W, H = 256, 192
NH = 42


@pytest.fixture(autouse=True)
def denormals_restored():
    yield
    torch.set_flush_denormal(False)


def rig() -> np.ndarray:
    return np.stack([projection(c.K, c.world_T_cam) for c in camera_specs(W, H)])


def objects_on_the_table() -> np.ndarray:
    """(8,3): the assembly's board and camera module posed on the table, 8 cm apart."""
    models = object_models("assembly")
    return np.concatenate([m.points + off for m, off in zip(models, ([0.05, -0.05, 0.0], [0.0, 0.05, 0.0]),
                                                            strict=True)])


def test_object_slices_group_each_objects_keypoints():
    names = keypoint_names("assembly")
    got = object_crops.object_slices(names, NH)
    assert [o for o, _ in got] == ["board", "camera"]
    assert got[0][1] == slice(42, 47) and got[1][1] == slice(47, 50)


def test_object_centres_ignore_exchanged_keypoints_and_need_two_views():
    rng = np.random.default_rng(1)
    P = rig()
    pts = objects_on_the_table()
    uv, _ = project(P, pts)
    uv = uv + rng.normal(0, 0.5, uv.shape)
    uv[:, [0, 3]] = uv[:, [3, 0]]  # every view exchanges two of the board's corners
    conf = np.ones(uv.shape[:2])
    slices = [slice(0, 5), slice(5, 8)]
    centres, found = object_crops.object_centres(P, uv, conf, slices)
    assert found.all()
    for o, sl in enumerate(slices):
        assert np.linalg.norm(centres[o] - np.median(pts[sl], axis=0)) < 0.01
    conf[1:, 5:] = 0.0  # the camera module in one view only
    _, found = object_crops.object_centres(P, uv, conf, slices)
    assert found.tolist() == [True, False]


def object_stage(tmp_path, peak_offset_px: float, keypoints: list[str] | None = None) -> LearnedDetector:
    names = keypoint_names("assembly")
    torch.save(UNet(len(names)).state_dict(), tmp_path / "weights.pt")
    (tmp_path / "meta.json").write_text(json.dumps({"task": "assembly", "keypoints": names, "input_size": [32, 24]}))
    torch.save(UNet(8).state_dict(), tmp_path / "objects.pt")
    (tmp_path / "objects.json").write_text(json.dumps({"input_size": 32, "half_size_m": 0.05,
                                                       "keypoints": keypoints or names[NH:]}))
    det = LearnedDetector(tmp_path, runtime="torch")
    ys, xs = np.mgrid[:32, :32]
    target = np.exp(-((xs - 15.5 - peak_offset_px) ** 2 + (ys - 15.5) ** 2) / (2 * 1.5**2)).astype(np.float32)
    det._run_object = lambda batch: np.broadcast_to(target, (len(batch), 8, 32, 32)).copy()
    return det


def test_the_object_stage_replaces_each_objects_peaks_around_its_centre(tmp_path):
    P = rig()
    pts = objects_on_the_table()
    truth, _ = project(P, pts)
    det = object_stage(tmp_path, peak_offset_px=4.0)  # every crop's peaks 4 crop pixels right of its centre
    views = [View(f"cam{i}", CameraModel(P[i], W, H, (0, 0, W, H)), np.zeros((H, W, 3), np.uint8))
             for i in range(len(P))]
    first = np.zeros((len(P), len(det.names), 2))
    first[:, NH:] = truth
    first[:, :NH] = 7.0
    conf = np.ones(first.shape[:2])
    uv = first.copy()
    det._refine_objects(views, [v.image for v in views], (first.copy(), conf.copy()), uv, conf)
    centres, _ = object_crops.object_centres(P, first, np.ones_like(conf), det.object_slices)
    f = np.array([hand_crops.focal_px(p) for p in P])
    box, half, _ = hand_crops.hand_boxes(P, centres, np.ones(2, bool), f, half_m=0.05)
    step = 4.0 * 2 * half / 32  # crop pixels -> image pixels, not mirrored
    assert np.allclose(uv[:, 42:47], (box[:, 0] + np.c_[step[:, 0], np.zeros(len(P))])[:, None], atol=1e-3)
    assert np.allclose(uv[:, 47:50], (box[:, 1] + np.c_[step[:, 1], np.zeros(len(P))])[:, None], atol=1e-3)
    assert np.allclose(uv[:, :NH], 7.0)  # hands keep what they had
    assert np.all(conf[:, NH:] > 0.9)


def test_the_object_stage_clears_views_whose_window_misses_the_object(tmp_path):
    det = object_stage(tmp_path, 0.0)
    P = rig()
    pix, _ = project(P, objects_on_the_table())
    corner = (0, 0, 56, 42)  # every view's window in the image's corner, far from the objects
    assert (pix[..., 0].min() > corner[2] + 20) and (pix[..., 1].min() > corner[3] + 20)
    views = [View(f"cam{i}", CameraModel(P[i], W, H, corner), np.zeros((42, 56, 3), np.uint8)) for i in range(len(P))]
    uv = np.zeros((len(P), len(det.names), 2))
    uv[:, NH:] = pix
    conf = np.ones(uv.shape[:2])
    det._refine_objects(views, [v.image for v in views], (uv.copy(), conf.copy()), uv, conf)
    assert (conf[:, NH:] == 0).all() and (conf[:, :NH] == 1).all() and np.isfinite(uv).all()


def test_object_stage_weights_for_other_keypoints_are_refused(tmp_path):
    with pytest.raises(ValueError, match="object stage"):
        object_stage(tmp_path, 0.0, keypoints=["box/top", "box/c0"])


def test_training_crops_hold_the_objects_keypoints_unmirrored_at_the_labels_scale():
    table = object_table("assembly")
    sl, model = table[0]
    img = np.zeros((120, 160, 3), np.uint8)
    uv = np.zeros((8, 2))
    uv[sl] = 80 + model[:, :2] * [400.0, -400.0]  # 400 px per metre, seen from above
    labelled = np.zeros(8, bool)
    labelled[sl] = True
    assert pixels_per_metre(uv[sl], labelled[sl], model) == pytest.approx(400.0, rel=0.01)
    x, y = crop_sample(img, uv, labelled, sl, model, 32, NO_AUGMENT, np.random.default_rng(2))
    assert x.shape == (3, 32, 32) and y.shape == (8, 32, 32)
    assert y[5:].max() == 0.0  # the camera module is not labelled
    got, _ = peaks(y[sl])
    assert np.argmin(got[:4, 0]) in (0, 3) and np.argmax(got[:4, 0]) in (1, 2)  # c0/c3 left, as in the image
    assert got[0, 1] > got[3, 1]  # c0 below c3: not mirrored
