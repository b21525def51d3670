"""recon's 3-D stages against synthetic truth: robust triangulation, the articulated hand model and
its per-frame fit, rigid objects (services/recon)."""

from __future__ import annotations

import numpy as np
import pytest

from services.recon.detector import CameraModel, SimulatedDetector
from services.recon.hand_fit import FitConfig, HandTracker
from services.recon.hand_model import (
    DEFAULT_BONES,
    DEFAULT_PALM,
    N_JOINTS,
    N_PARAMS,
    HandShape,
    forward,
    forward_jacobian,
    joint_bounds,
    rodrigues,
    rotvec,
)
from services.recon.objects import object_models, pose_objects, task_keypoint_names
from services.recon.pipeline import Reconstructor, beyond_the_hand, one_hand_seen_twice
from services.recon.triangulation import project, triangulate, triangulate_robust
from shared.geometry import look_at, projection


@pytest.fixture
def rig() -> list[CameraModel]:
    K = np.array([[280.0, 0, 160], [0, 280.0, 120], [0, 0, 1]])
    eyes = [np.array([0.4 * np.cos(a), 0.4 * np.sin(a), 0.8]) for a in np.linspace(0, 2 * np.pi, 7, endpoint=False)]
    return [CameraModel(projection(K, look_at(e, np.zeros(3))), 320, 240) for e in eyes]


def _shape() -> HandShape:
    frames = np.repeat(np.eye(3)[None], 5, axis=0)
    x = np.array([0.6, 0.7, -0.4]) / np.linalg.norm([0.6, 0.7, -0.4])
    z = np.array([0.0, 0.0, 1.0]) - x[2] * x
    z /= np.linalg.norm(z)
    frames[0] = np.stack([x, np.cross(z, x), z], axis=1)
    return HandShape(DEFAULT_PALM.copy(), DEFAULT_BONES.copy(), frames)


def _pose(t: float, side: str) -> np.ndarray:
    """A hand moving and curling its fingers over time t (s)."""
    p = np.zeros(N_PARAMS)
    p[:3] = [0.2 * np.sin(t), 0.3, 0.5 * t]
    p[3:6] = [0.05 * np.cos(t), 0.03 * t, 0.1]
    p[6:6 + N_JOINTS] = np.tile([0.1 * np.sin(2 * t), 0.4 + 0.3 * np.sin(t), 0.5, 0.3], 5)
    return p


# --- triangulation ------------------------------------------------------------------------
def test_robust_triangulation_rejects_outlier_views_that_ruin_dlt(rig):
    rng = np.random.default_rng(4)
    pts = rng.uniform([-0.15, -0.15, 0.0], [0.15, 0.15, 0.15], (60, 3))
    uv, seen = SimulatedDetector(pixel_noise=1.0, dropout=0.0, seed=5).detect(rig, pts)
    bad = rng.random(seen.shape) < 0.15  # 15 % of detections land somewhere wrong
    uv[bad] += rng.uniform(30, 80, (int(bad.sum()), 2)) * rng.choice([-1, 1], (int(bad.sum()), 2))
    P = np.stack([c.P for c in rig])
    dlt, _ = triangulate(P, uv, seen)
    robust, ok, inliers = triangulate_robust(P, uv, seen.astype(float))
    assert ok.all()
    err_dlt = np.linalg.norm(dlt - pts, axis=1).mean()
    err = np.linalg.norm(robust - pts, axis=1).mean()
    assert err < 0.004 < err_dlt
    assert not (inliers & bad).any(), "every corrupted view is left out"


def test_points_fewer_than_two_views_saw_are_masked_zero_never_nan(rig):
    pts = np.array([[0.0, 0.0, 0.05], [0.05, 0.0, 0.05], [0.0, 0.05, 0.05]])
    uv, seen = SimulatedDetector(pixel_noise=0.0, dropout=0.0).detect(rig, pts)
    seen[:, 1] = False
    seen[1:, 2] = False  # one view only
    uv[:, 1] = np.nan  # a detector's NaN for a missed point must not leak either
    est, ok, inliers = triangulate_robust(np.stack([c.P for c in rig]), uv, seen.astype(float))
    assert ok.tolist() == [1, 0, 0]
    assert np.isfinite(est).all() and (est[1:] == 0).all()
    assert not inliers[:, 1:].any()
    np.testing.assert_allclose(est[0], pts[0], atol=1e-6)


def test_a_missing_camera_leaves_the_others_to_triangulate(rig):
    pts = np.array([[0.02, -0.03, 0.04]])
    uv, seen = SimulatedDetector(pixel_noise=0.0, dropout=0.0).detect(rig[2:4], pts)
    est, ok, _ = triangulate_robust(np.stack([c.P for c in rig[2:4]]), uv, seen.astype(float))
    assert ok[0] == 1
    np.testing.assert_allclose(est[0], pts[0], atol=1e-6)


# --- the hand model -----------------------------------------------------------------------
@pytest.mark.parametrize("side", ["left", "right"])
def test_hand_model_jacobian_matches_finite_differences(side):
    shape, p = _shape(), _pose(0.7, side)
    p[6 + N_JOINTS:] = [0.1, -0.05, 0.02]
    pts, J = forward_jacobian(shape, p, side)
    np.testing.assert_allclose(pts, forward(shape, p, side), atol=1e-12)
    for i in range(N_PARAMS):
        d = np.zeros(N_PARAMS)
        d[i] = 1e-6
        num = (forward(shape, p + d, side) - forward(shape, p - d, side)) / 2e-6
        np.testing.assert_allclose(J[:, :, i], num, atol=1e-7)


def test_left_hand_is_the_mirror_image_of_the_right():
    shape, p = _shape(), _pose(0.0, "right")
    p[:6] = 0.0
    right, left = forward(shape, p, "right"), forward(shape, p, "left")
    np.testing.assert_allclose(left, right * [1, -1, 1], atol=1e-12)


def _track(tracker: HandTracker, shape: HandShape, times, side: str, noise: float, rng, hide=(),
           hidden_frames=()) -> list:
    errs = []
    for i, t in enumerate(times):
        truth = forward(shape, _pose(t, side), side)
        obs = truth + rng.normal(0, noise, truth.shape)
        mask = np.ones(21, bool)
        if i in hidden_frames:
            mask[list(hide)] = False
        out, out_mask, fitted = tracker.update(obs, mask, np.full(21, 4.0))
        errs.append((np.linalg.norm(out - truth, axis=1), out_mask, fitted))
    return errs


@pytest.mark.parametrize("side", ["left", "right"])
def test_tracker_learns_the_shape_then_fits_below_the_noise_and_fills_occluded_fingers(side):
    rng = np.random.default_rng(0)
    shape, tracker = _shape(), HandTracker(side, FitConfig(init_frames=8))
    init = _track(tracker, shape, np.arange(8) * 0.1, side, 0.002, rng)
    assert not any(f for _, _, f in init) and tracker.shape is not None
    np.testing.assert_allclose(tracker.shape.bones[1:], shape.bones[1:], atol=0.003)
    hidden = (10, 11)
    fit = _track(tracker, shape, 0.8 + np.arange(20) * 0.05, side, 0.002, rng, hide=(6, 7, 8), hidden_frames=hidden)
    assert all(f for _, _, f in fit)
    err = np.stack([e for e, _, _ in fit])
    seen = np.ones(err.shape, bool)
    seen[np.ix_(hidden, [6, 7, 8])] = False
    raw = 0.002 * np.sqrt(8 / np.pi)  # mean norm of the observations' 3-D noise: 3.2 mm
    assert err[seen].mean() < 0.85 * raw, "the model averages part of the noise away"
    # held near its last estimate: about a centimetre at worst with 2 mm noise on what is seen
    assert err[np.ix_(hidden, [6, 7, 8])].max() < 0.012, "the briefly hidden index finger comes from the model"
    assert all(m.all() for _, m, _ in fit)
    lo, hi = joint_bounds()
    last = tracker._window[-1]
    assert ((last >= lo - 1e-9) & (last <= hi + 1e-9)).all(), "joint limits hold"


def test_hand_leaving_the_rig_resets_the_fit_which_restarts_where_it_returns():
    rng = np.random.default_rng(1)
    shape, tracker = _shape(), HandTracker("right", FitConfig(init_frames=8, lost_after=3))
    _track(tracker, shape, np.arange(12) * 0.1, "right", 0.001, rng)
    assert tracker.tracking
    for _ in range(3):
        out, mask, fitted = tracker.update(np.full((21, 3), np.nan), np.zeros(21, bool))
        assert not fitted and not mask.any() and np.isfinite(out).all()
    assert not tracker.tracking and tracker.resets == 1
    far = _track(tracker, shape, [4.0], "right", 0.001, rng)  # back elsewhere, turned by 2 rad
    err, _, fitted = far[0]
    assert fitted and err.max() < 0.005


def test_a_fitted_keypoint_is_the_mean_of_the_model_and_its_triangulation():
    rng = np.random.default_rng(2)
    shape, tracker = _shape(), HandTracker("right", FitConfig(init_frames=8))
    _track(tracker, shape, np.arange(10) * 0.1, "right", 0.001, rng)
    obs = forward(shape, _pose(1.05, "right"), "right")
    obs[8] += [0.004, 0.0, 0.0]  # a fingertip 4 mm off: too little to override the model
    mask = np.ones(21, bool)
    mask[12] = False  # not triangulated: the model alone
    out, out_mask, fitted = tracker.update(obs, mask, np.full(21, 2.0))
    model = forward(tracker.shape, tracker.last_params, "right")
    assert fitted and out_mask.all() and tracker.overridden == 0
    np.testing.assert_allclose(out[mask], 0.5 * (model[mask] + obs[mask]), atol=1e-12)
    np.testing.assert_allclose(out[12], model[12], atol=1e-12)
    assert abs(out[8, 0] - model[8, 0]) > 1e-4, "the observation pulls the fingertip off the model"


def test_rotvec_inverts_rotation_near_half_turn():
    for r in ([0.1, -0.2, 0.3], [0.0, 0.0, np.pi - 1e-4], [2.0, 1.0, -1.5]):
        R = rodrigues(np.array(r))
        np.testing.assert_allclose(rodrigues(rotvec(R)), R, atol=1e-6)


# --- rigid objects ------------------------------------------------------------------------
def test_object_posed_from_three_keypoints_fills_the_rest_and_drops_a_wrong_one():
    models = object_models("assembly")
    names = task_keypoint_names("assembly")
    assert len(names) == sum(len(m.points) for m in models)
    board = models[0]
    yaw = 0.7
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    t = np.array([0.05, -0.04, 0.0])
    truth = np.concatenate([m.points for m in models]) @ R.T + t
    mask = np.zeros(len(names), np.uint8)
    mask[board.slice] = [1, 1, 1, 1, 0]  # connector unseen
    obs = truth.copy()
    obs[1] += [0.02, 0.0, 0.0]  # a corner 2 cm off: not the object
    out, out_mask, posed, _, _ = pose_objects(models, obs, mask)
    assert posed.tolist() == [True, False]
    np.testing.assert_allclose(out[board.slice], truth[board.slice], atol=1e-9)
    assert out_mask[board.slice].all()
    assert not out_mask[models[1].slice].any() and (out[models[1].slice] == 0).all()


def test_an_object_without_a_track_is_reported_once_two_frame_sets_agree(rig):
    """A network's object peaks on something else (a hand, after a reset moved the objects out of
    every window) pose the object where it is not, once; a new track waits for a second frame set
    at the same place, and a tracked object is reported on every frame set."""
    P = np.stack([c.P for c in rig])
    models = object_models("assembly")
    here = np.concatenate([m.points + [0.1 * i, 0.0, 0.0] for i, m in enumerate(models)])
    elsewhere = here + [-0.15, 0.1, 0.2]
    rec = Reconstructor("assembly")
    nh = 2 * 21
    masks = []
    for objects in (elsewhere, here, here, here):
        uv, _ = project(P, np.concatenate([np.zeros((nh, 3)), objects]))
        conf = np.zeros(uv.shape[:2])
        conf[:, nh:] = 1.0
        r = rec.step(P, uv, conf)
        masks.append(r.object_mask.astype(bool))
        assert r.object_posed.all() == r.object_mask.all(), "an unconfirmed object is not posed either"
        if r.object_mask.any():
            np.testing.assert_allclose(r.objects, objects, atol=1e-3)
    assert [m.any() for m in masks] == [False, False, True, True]
    assert all(m.all() for m in masks[2:])
    assert rec.objects_unconfirmed == 2 * len(models)
    plain = Reconstructor("assembly", confirm_objects=False)
    uv, _ = project(P, np.concatenate([np.zeros((nh, 3)), elsewhere]))
    conf = np.zeros(uv.shape[:2])
    conf[:, nh:] = 1.0
    assert plain.step(P, uv, conf).object_mask.all(), "without confirmation the first pose is reported"


def test_object_with_two_keypoints_stays_triangulated():
    models = object_models("pick_place")
    pts = np.random.default_rng(2).uniform(-0.1, 0.1, (sum(len(m.points) for m in models), 3))
    mask = np.zeros(len(pts), np.uint8)
    mask[models[0].slice.start:models[0].slice.start + 2] = 1
    out, out_mask, posed, _, _ = pose_objects(models, pts, mask)
    assert not posed.any()
    np.testing.assert_array_equal(out_mask, mask)
    np.testing.assert_allclose(out[mask == 1], pts[mask == 1])


def test_unknown_task_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown task"):
        object_models("juggling")


def test_a_hand_triangulated_onto_the_other_is_dropped_not_reported_twice():
    """Both hands' keypoints on one physical hand (a detector's left and right channels peaking on
    the one hand a window shows): the hand with the weaker detections is masked."""
    rng = np.random.default_rng(5)
    hand = rng.uniform(-0.05, 0.05, (21, 3)) + [0.1, 0.0, 0.2]
    mask = np.ones((2, 21), np.uint8)
    twice = np.stack([hand, hand + rng.normal(0, 0.005, hand.shape)])
    assert one_hand_seen_twice(twice, mask, np.array([0.9, 0.6])) == 1
    assert one_hand_seen_twice(twice, mask, np.array([0.5, 0.8])) == 0
    apart = np.stack([hand, hand + [0.0, 0.3, 0.0]])
    assert one_hand_seen_twice(apart, mask, np.array([0.9, 0.6])) is None
    few = mask.copy()
    few[1, 4:] = 0  # too few keypoints of the second hand to tell
    assert one_hand_seen_twice(twice, few, np.array([0.9, 0.6])) is None


def test_a_keypoint_far_from_the_rest_of_its_hand_is_masked():
    rng = np.random.default_rng(6)
    hand = rng.uniform(-0.04, 0.04, (21, 3)) + [0.1, 0.0, 0.2]
    mask = np.ones(21, np.uint8)
    assert not beyond_the_hand(hand, mask).any()
    hand[8] += [0.0, 0.3, 0.0]  # the index tip triangulated on the other hand
    assert np.flatnonzero(beyond_the_hand(hand, mask)).tolist() == [8]
    few = np.zeros(21, np.uint8)
    few[[0, 8]] = 1  # too few keypoints to tell where the hand is
    assert not beyond_the_hand(hand, few).any()
