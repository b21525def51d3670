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


def object_stage(tmp_path, peak_offset_px: float, keypoints: list[str] | None = None, amplitude: float = 1.0,
                 **options) -> LearnedDetector:
    names = keypoint_names("assembly")
    torch.save(UNet(len(names)).state_dict(), tmp_path / "weights.pt")
    (tmp_path / "meta.json").write_text(json.dumps({"task": "assembly", "keypoints": names, "input_size": [32, 24]}))
    torch.save(UNet(8).state_dict(), tmp_path / "objects.pt")
    (tmp_path / "objects.json").write_text(json.dumps({"input_size": 32, "half_size_m": 0.05,
                                                       "keypoints": keypoints or names[NH:]}))
    det = LearnedDetector(tmp_path, runtime="torch", **options)
    ys, xs = np.mgrid[:32, :32]
    target = amplitude * np.exp(-((xs - 15.5 - peak_offset_px) ** 2 + (ys - 15.5) ** 2) / (2 * 1.5**2))
    target = target.astype(np.float32)
    det.batches = []  # crops per network call

    def run(batch: np.ndarray) -> np.ndarray:
        det.batches.append(len(batch))
        return np.broadcast_to(target, (len(batch), 8, 32, 32)).copy()
    det._run_object = run
    return det


def test_the_object_stage_replaces_each_objects_peaks_around_its_centre(tmp_path):
    P = rig()
    pts = objects_on_the_table()
    truth, _ = project(P, pts)
    det = object_stage(tmp_path, peak_offset_px=4.0, object_views=0)  # peaks 4 crop pixels right of its centre
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


@pytest.mark.parametrize("threshold, kept", [(None, False), (0.4, True), (0.0, True)])
def test_weak_object_crops_are_dropped_as_missed(tmp_path, threshold, kept):
    P = rig()
    truth, _ = project(P, objects_on_the_table())
    det = object_stage(tmp_path, 0.0, amplitude=0.5, object_views=0, object_present_confidence=threshold,
                       object_verify_shift=0.0)  # the stub's peaks follow the crop: no twin check here
    assert det.object_present_confidence == (object_crops.PRESENT_CONFIDENCE if threshold is None else threshold)
    views = [View(f"cam{i}", CameraModel(P[i], W, H, (0, 0, W, H)), np.zeros((H, W, 3), np.uint8))
             for i in range(len(P))]
    uv = np.zeros((len(P), len(det.names), 2))
    uv[:, NH:] = truth
    conf = np.ones(uv.shape[:2])
    det._refine_objects(views, [v.image for v in views], (uv.copy(), conf.copy()), uv, conf)
    assert det.object_crops > 0 and np.isfinite(uv).all()
    if kept:
        assert np.all(conf[:, NH:] > 0.4) and det.object_crops_missed == 0
    else:  # peaks of 0.5 under the default 0.6: every crop missed its object
        assert np.all(conf[:, NH:] == 0.0) and det.object_crops_missed == det.object_crops


def test_disagreement_is_the_median_distance_over_keypoints_confident_in_both():
    a = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    b = a + [[0.5, 0.0], [0.0, 2.0], [9.0, 9.0]]
    assert object_crops.disagreement(a, np.ones(3), b, np.ones(3)) == pytest.approx(2.0)
    assert object_crops.disagreement(a, np.ones(3), b, np.array([1.0, 0.1, 0.1])) == pytest.approx(0.5)
    assert object_crops.disagreement(a, np.zeros(3), b, np.ones(3)) == np.inf


def dot_images(P: np.ndarray, point: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """One bright blur (sigma 1 px) per view at ``point``'s projection; and those pixels (C,2)."""
    pix, _ = project(P, point[None])
    ys, xs = np.mgrid[:H, :W]
    images = []
    for u, v in pix[:, 0]:
        blob = 255.0 * np.exp(-((xs - u) ** 2 + (ys - v) ** 2) / 2.0)
        images.append(np.repeat(blob[..., None], 3, axis=2).astype(np.uint8))
    return images, pix[:, 0]


def image_tied(det: LearnedDetector, amplitude: float) -> None:
    """The object stage stand-in puts every peak on the crop's bright spot (its intensity centroid),
    wherever the crop lies: peaks on something in the image, as on an object the crop shows."""
    ys, xs = np.mgrid[:32, :32]

    def run(batch: np.ndarray) -> np.ndarray:
        det.batches.append(len(batch))
        out = np.zeros((len(batch), 8, 32, 32), np.float32)
        for i, crop in enumerate(batch):
            w = crop[0]
            if w.sum() > 1e-3:
                cx, cy = (xs * w).sum() / w.sum(), (ys * w).sum() / w.sum()
                out[i] = amplitude * np.exp(-((xs - cx) ** 2 + (ys - cy) ** 2) / (2 * 1.5**2))
        return out
    det._run_object = run


@pytest.mark.parametrize("tied", ["image", "crop"])
def test_a_crop_whose_peaks_follow_a_shifted_twin_is_dropped(tmp_path, tied):
    P = rig()
    truth, _ = project(P, objects_on_the_table())
    board = objects_on_the_table()[:5].mean(axis=0) + [0.01, 0.005, 0.0]  # off the crop's centre
    images, spot = dot_images(P, board)
    det = object_stage(tmp_path, peak_offset_px=0.0, amplitude=0.7)  # kept (>= 0.6), not trusted (< 0.8)
    if tied == "image":
        image_tied(det, 0.7)
    views = [View(f"cam{i}", CameraModel(P[i], W, H, (0, 0, W, H)), images[i]) for i in range(len(P))]
    first = np.zeros((len(P), len(det.names), 2))
    first[:, NH:] = truth
    conf = np.ones(first.shape[:2])
    uv = first.copy()
    det._refine_objects(views, images, (first.copy(), conf.copy()), uv, conf)
    # the crops, then in one call the twins of those kept but not trusted (the image-tied stand-in
    # sees nothing in the camera module's crops: confidence 0, no twin)
    assert det.batches == ([6, 3] if tied == "image" else [6, 6])
    cropped = conf[:, NH:NH + 5].any(axis=1)
    if tied == "image":
        assert cropped.sum() == 3 and det.object_crops_unsteady == 0
        assert np.abs(uv[cropped, NH:NH + 5] - spot[cropped, None]).max() < 0.5
        assert np.allclose(conf[cropped, NH:NH + 5], 0.7, atol=0.01)
    else:  # the peaks sit at the crop's centre wherever it is: the twin's lie 0.3 half sides off
        assert not cropped.any() and det.object_crops_unsteady == 6 and det.object_crops_missed == 0


def test_trusted_crops_are_not_checked_by_a_twin(tmp_path):
    P = rig()
    truth, _ = project(P, objects_on_the_table())
    det = object_stage(tmp_path, peak_offset_px=0.0, amplitude=0.9)
    views = full_views(P, det)
    first = np.zeros((len(P), len(det.names), 2))
    first[:, NH:] = truth
    conf = np.ones(first.shape[:2])
    det._refine_objects(views, [v.image for v in views], (first.copy(), conf.copy()), first.copy(), conf)
    assert det.batches == [6] and det.object_crops_unsteady == 0
    assert (conf[:, NH:] > 0.8).sum(axis=0).tolist() == [3] * 8


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


def full_views(P: np.ndarray, det: LearnedDetector) -> list[View]:
    return [View(f"cam{i}", CameraModel(P[i], W, H, (0, 0, W, H)), np.zeros((H, W, 3), np.uint8))
            for i in range(len(P))]


def test_view_scores_rank_by_projected_size_and_drop_views_that_miss_or_are_covered():
    P = rig()
    pts = objects_on_the_table()
    centres = np.stack([pts[:5].mean(axis=0), pts[5:].mean(axis=0)])
    f = np.array([hand_crops.focal_px(p) for p in P])
    full = np.tile([0.0, 0.0, W, H], (len(P), 1))
    plain = object_crops.view_scores(P, f, full, centres, np.ones(2, bool), [None, None])
    assert (plain > 0).all()
    depth = project(P, centres)[1]
    assert np.argmax(plain[:, 0]) == np.argmin(depth[:, 0])  # without keypoints: the nearest camera
    # A window that misses the object, and an object not wanted, score 0.
    windows = full.copy()
    windows[2] = (0, 0, 10, 10)
    got = object_crops.view_scores(P, f, windows, centres, np.array([True, False]), [None, None])
    assert got[2, 0] == 0 and (got[:, 1] == 0).all() and (got[np.arange(len(P)) != 2, 0] > 0).all()
    # Keypoints give the projected extent: the board's long side seen end-on ranks below seen broadside.
    flat = object_crops.view_scores(P, f, full, centres, np.ones(2, bool), [pts[:5], pts[5:]])
    assert (flat > 0).all() and not np.allclose(flat[:, 0] / plain[:, 0], flat[0, 0] / plain[0, 0])
    # A hand between camera 0 and the board covers it there, and only there.
    eye = -np.linalg.solve(P[0][:, :3], P[0][:, 3])
    hand = centres[0] + 0.3 * (eye - centres[0])
    one = np.ones(1, bool)
    covered = object_crops.view_scores(P, f, full, centres, np.ones(2, bool), [None, None], hand[None], one)
    assert covered[0, 0] < 0.1 * plain[0, 0]
    hpix, hz = project(P, hand[None])
    opix, oz = project(P, centres[:1])
    apart = np.linalg.norm(hpix[:, 0] - opix[:, 0], axis=-1) > f * (object_crops.HAND_RADIUS_M / hz[:, 0]
                                                                     + object_crops.EXTENT_M / oz[:, 0])
    assert apart[1:].any() and np.allclose(covered[apart, 0], plain[apart, 0])
    # An unfound hand covers nothing.
    assert np.allclose(object_crops.view_scores(P, f, full, centres, np.ones(2, bool), [None, None], hand[None],
                                                np.zeros(1, bool)), plain)


def test_choose_views_keeps_the_best_k_and_none_below_two():
    scores = np.array([[5.0, 1.0], [3.0, 0.0], [4.0, 0.0], [1.0, 0.0]])
    got = object_crops.choose_views(scores, 2)
    assert got[:, 0].tolist() == [True, False, True, False]
    assert not got[:, 1].any()  # one view shows the second object: not triangulable
    assert object_crops.choose_views(scores, 0)[:, 0].all()


def test_schedule_crops_moving_objects_every_time_and_resting_ones_in_turn():
    s = object_crops.ObjectSchedule(2)
    centres, found = np.array([[0.0, 0, 0], [0.2, 0, 0]]), np.ones(2, bool)
    refresh, reuse = s.plan(centres, found)
    assert refresh.all() and not reuse.any()  # new objects
    for o in range(2):
        s.store(o, centres[o], {"cam0": (np.zeros((1, 2)), np.ones(1))}, None)
    plans = []
    for _ in range(4):
        refresh, reuse = s.plan(centres, found)
        plans.append((refresh.tolist(), reuse.tolist()))
        for o in np.flatnonzero(refresh):
            s.store(o, centres[o], {}, None)
        for o in np.flatnonzero(reuse):
            s.reuse(o)
    # At rest: both just cropped are reused, then they take turns, one crop per frame set.
    assert plans[0] == ([False, False], [True, True])
    assert [r for r, _ in plans[1:]] == [[True, False], [False, True], [True, False]]
    assert all([a or b for a, b in zip(r, u, strict=True)] == [True, True] for r, u in plans)
    moved = centres + [[0.05, 0, 0], [0, 0, 0]]  # the board is picked up
    refresh, reuse = s.plan(moved, found)
    assert refresh[0] and not reuse[0]
    refresh, reuse = s.plan(centres, np.array([True, False]))  # the camera module is lost
    assert s.held[1] is None and not refresh[1] and not reuse[1]
    s.store(0, centres[0], {}, None)
    assert s.plan(centres, found)[1][0]  # the board rests again
    refresh, reuse = s.plan(centres, found, busy=np.array([True, False]))  # a hand is at it: it may move
    assert refresh[0] and not reuse[0]
    every = object_crops.ObjectSchedule(2, reuse=False)
    for o in range(2):
        every.store(o, centres[o], {}, None)
    assert every.plan(centres, found)[0].all()


def test_an_untouched_object_stays_where_it_was_placed_until_a_crop_there_misses():
    s = object_crops.ObjectSchedule(2)
    placed = np.array([[0.0, 0, 0], [0.2, 0, 0]])
    for o in range(2):
        s.store(o, placed[o], {}, placed[o] + np.array([[0.02, 0, 0], [-0.02, 0, 0]]))
    no_hands = np.zeros((0, 3))
    # the first stage misses the camera module and puts the board 13 cm off (a full frame)
    first = np.array([[0.13, 0, 0], [0.0, 0, 0]])
    centres, found, kept = s.track(first, np.array([True, False]), no_hands)
    np.testing.assert_array_equal(centres, placed)
    assert found.all() and kept.all() and s.kept_in_place == 2
    # a first-stage centre within JUMP_M stands, and so does anything a hand is near
    near = placed + [[0.01, 0, 0], [0, 0, 0]]
    centres, found, kept = s.track(near, np.ones(2, bool), no_hands)
    np.testing.assert_array_equal(centres, near)
    assert not kept.any()
    centres, found, kept = s.track(first, np.array([True, False]), np.array([[-0.05, 0, 0]]))  # a hand at the board
    np.testing.assert_array_equal(centres[0], first[0])
    assert kept.tolist() == [False, True]
    # a crop at the kept place that placed nothing (the object was moved all the same): let go
    s.store(1, placed[1], {}, None)
    centres, found, kept = s.track(first, np.array([True, False]), no_hands)
    assert not found[1] and not kept[1]


def test_the_object_stage_crops_the_best_views_and_reuses_a_resting_objects_detections(tmp_path):
    P = rig()
    truth, _ = project(P, objects_on_the_table())
    det = object_stage(tmp_path, peak_offset_px=0.0)  # three views per object, resting objects reused
    views = full_views(P, det)
    first = np.zeros((len(P), len(det.names), 2))
    first[:, NH:] = truth
    conf = np.ones(first.shape[:2])

    def frame_set() -> tuple[np.ndarray, np.ndarray]:
        uv, c = first.copy(), conf.copy()
        det._refine_objects(views, [v.image for v in views], (first.copy(), conf.copy()), uv, c)
        return uv, c

    uv1, c1 = frame_set()
    assert det.batches == [6]  # both objects, three views each, one network call
    for sl in det.object_slices:
        cropped = (c1[:, sl] > 0.9).all(axis=1)
        assert cropped.sum() == 3 and (c1[~cropped, sl] == 0).all()  # the other views are silenced
    # Nothing moves: both objects' detections are reused, then one object at a time is cropped again.
    for _ in range(3):
        uv, c = frame_set()
        assert np.array_equal(c1 > 0, c > 0) and np.allclose(uv1[c1 > 0], uv[c > 0])
    assert det.batches == [6, 3, 3]
    det.reset()
    frame_set()
    assert det.batches[-1] == 6


@pytest.mark.parametrize("hand_at_board", [False, True])
def test_an_object_a_hand_is_at_is_cropped_on_every_frame_set(tmp_path, hand_at_board):
    P = rig()
    pts = objects_on_the_table()
    truth, _ = project(P, pts)
    det = object_stage(tmp_path, peak_offset_px=0.0)
    views = full_views(P, det)
    first = np.zeros((len(P), len(det.names), 2))
    first[:, NH:] = truth
    conf = np.ones(first.shape[:2])
    board = pts[:5].mean(axis=0)
    hands = (np.array([board + [0.05, -0.05, 0.0], [0.5, 0.5, 0.3]]), np.array([hand_at_board, False]))
    for _ in range(2):
        det._refine_objects(views, [v.image for v in views], (first.copy(), conf.copy()), first.copy(), conf.copy(),
                            hands=hands)
    # both resting: reused on the second frame set; the board with a hand 7 cm away is cropped again
    assert det.batches == ([6, 3] if hand_at_board else [6])
