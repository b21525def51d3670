"""Rigid objects posed on their 2-D detections (services/recon/object_fit.py)."""

from __future__ import annotations

import numpy as np

from services.recon import object_fit
from services.recon.hand_model import rodrigues
from services.recon.object_fit import RigidTracker, fit_pose, hypotheses, reprojection
from services.recon.objects import object_models
from services.recon.pipeline import Reconstructor
from services.world.model import camera_specs
from shared.geometry import projection

BOARD = object_models("assembly")[0].points  # 5 keypoints, 6 x 3 cm


def rig() -> np.ndarray:
    return np.stack([projection(c.K, c.world_T_cam) for c in camera_specs(256, 192)])


def detections(P: np.ndarray, X: np.ndarray, rng: np.random.Generator, noise_px: float, outliers: float,
               swap: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Projected keypoints with pixel noise; ``outliers`` of them anywhere within 40 px; ``swap`` of
    the views with two corners exchanged (a consistent mistake within the view)."""
    h = np.einsum("cij,kj->cki", P, np.c_[X, np.ones(len(X))])
    uv = h[..., :2] / h[..., 2:3] + rng.normal(0, noise_px, h[..., :2].shape)
    bad = rng.random(uv.shape[:2]) < outliers
    uv[bad] += rng.uniform(-40, 40, (bad.sum(), 2))
    for c in np.flatnonzero(rng.random(len(P)) < swap):
        uv[c, [0, 3]] = uv[c, [3, 0]]
    return uv, np.ones(uv.shape[:2])


def pose(yaw: float, t: tuple) -> tuple[np.ndarray, np.ndarray]:
    return rodrigues(np.array([0.02, -0.03, yaw])), np.array(t, float)


def test_fit_recovers_a_known_pose_from_noisy_detections_with_outliers() -> None:
    rng = np.random.default_rng(3)
    P = rig()
    R, t = pose(0.4, (0.05, -0.07, 0.02))
    truth = BOARD @ R.T + t
    errors = []
    for _ in range(10):
        uv, w = detections(P, truth, rng, 1.0, 0.25)
        # a poor start: the true pose turned by 20 degrees and moved 2 cm
        start = (rodrigues(np.array([0.0, 0.0, 0.35])) @ R, t + [0.02, 0.0, 0.0])
        fit = fit_pose(P, BOARD, uv, w, [start])
        assert fit is not None
        errors.append(np.linalg.norm(fit.points(BOARD) - truth, axis=1).mean())
    assert np.mean(errors) < 0.004  # metres: 1 px is about 5 mm at this rig's distance
    assert fit.inliers.mean() < 0.9  # the outliers were recognised as such


def test_outliers_would_spoil_a_plain_fit() -> None:
    """The robust loss matters: with it the pose holds, with a quadratic loss the outliers pull it."""
    rng = np.random.default_rng(4)
    P = rig()
    R, t = pose(-0.3, (0.0, -0.05, 0.02))
    truth = BOARD @ R.T + t
    uv, w = detections(P, truth, rng, 0.5, 0.3)
    robust = object_fit.refine(P, BOARD, uv, w, R, t)
    plain = object_fit.refine(P, BOARD, uv, w, R, t, scale_px=1e6)  # Cauchy with a huge scale: quadratic
    err = [np.linalg.norm(BOARD @ Rf.T + tf - truth, axis=1).mean() for Rf, tf in (robust, plain)]
    assert err[0] < 0.5 * err[1]


def test_hypotheses_survive_one_wrong_triangulated_keypoint() -> None:
    R, t = pose(1.0, (0.02, 0.0, 0.02))
    pts = BOARD @ R.T + t
    pts[2] += [0.03, -0.02, 0.01]  # one keypoint triangulated on something else
    starts = hypotheses(BOARD, pts, np.ones(5, bool))
    best = min(np.linalg.norm(BOARD @ Rs.T + ts - (BOARD @ R.T + t), axis=1).max() for Rs, ts in starts)
    assert best < 1e-9  # a triple without the wrong keypoint gives the exact pose


def test_reprojection_is_infinite_behind_the_camera() -> None:
    P = rig()[:1]
    err = reprojection(P, BOARD, np.eye(3), np.array([0.0, 0.0, 5.0]), np.zeros((1, 5, 2)))
    assert np.isinf(err).all()


def test_resting_object_pools_frames_and_a_move_restarts_the_window() -> None:
    rng = np.random.default_rng(5)
    P = rig()
    R, t = pose(0.2, (0.04, -0.06, 0.0))
    truth = BOARD @ R.T + t
    tracker = RigidTracker(BOARD, window=20)
    single, pooled = [], []
    for i in range(20):
        uv, w = detections(P, truth, rng, 2.0, 0.2, swap=0.15)
        fit = tracker.update(P, uv, w, truth + rng.normal(0, 0.004, truth.shape), np.ones(5, bool))
        assert fit is not None
        own = fit_pose(P, BOARD, uv, w, hypotheses(BOARD, truth, np.ones(5, bool)))
        single.append(np.linalg.norm(own.points(BOARD) - truth, axis=1).mean())
        if i >= 10:
            pooled.append(np.linalg.norm(fit.points(BOARD) - truth, axis=1).mean())
    assert tracker.restarts == 0
    assert np.mean(pooled) < 0.6 * np.mean(single)  # the window averages the per-frame errors
    moved = BOARD @ R.T + t + [0.05, 0.0, 0.0]
    uv, w = detections(P, moved, rng, 1.0, 0.0)
    fit = tracker.update(P, uv, w, moved, np.ones(5, bool))
    assert tracker.restarts == 1
    assert np.linalg.norm(fit.points(BOARD) - moved, axis=1).max() < 0.01  # not dragged behind


def test_pipeline_reports_the_posed_objects_from_detections() -> None:
    rng = np.random.default_rng(6)
    P = rig()
    rec = Reconstructor("assembly", object_fit="reprojection")
    models = object_models("assembly")
    R, t = pose(0.3, (0.05, -0.07, 0.0))
    board = models[0].points @ R.T + t
    R2, t2 = pose(3.0, (0.0, 0.08, 0.0))
    cam = models[1].points @ R2.T + t2
    objects = np.concatenate([board, cam])
    for _ in range(5):
        uv_o, _ = detections(P, objects, rng, 1.0, 0.15)
        uv = np.concatenate([np.zeros((len(P), 42, 2)), uv_o], axis=1)
        conf = np.concatenate([np.zeros((len(P), 42)), np.ones((len(P), len(objects)))], axis=1)
        r = rec.step(P, uv, conf)
    assert r.object_mask.all() and r.object_posed.all()
    assert np.linalg.norm(r.objects - objects, axis=1).mean() < 0.004
    assert not np.isnan(r.hands).any()
