"""The multi-camera calibration (``calibration/``) on synthetic detections: recovery of the truth,
robustness to outliers, and the named failures of bad captures."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.board import settings_from_table
from calibration.detect import Detections, add_view, degenerate
from calibration.init import CaptureUnusableError, average_pose
from calibration.pipeline import calibrate
from calibration.report import rotation_deg, truth_errors
from calibration.synthetic import project_views
from services.world import calibration_sequence as calseq
from services.world.model import CALIB_BOARD, build_model
from shared.calibration import from_json, to_json
from shared.charuco import BoardError, BoardSpec
from shared.geometry import look_at

BOARD = BoardSpec()
SIZE = (640, 480)


def rig(n: int = 3) -> tuple[list[str], list[np.ndarray], list[np.ndarray]]:
    """``n`` cameras on a ring 0.8 m up, looking at the table centre, slightly different lenses."""
    names, K, poses = [], [], []
    for i in range(n):
        a = 2 * np.pi * i / n
        f = 420.0 + 10 * i
        K.append(np.array([[f, 0, 320.0 + 3 * i], [0, f * 1.001, 240.0 - 2 * i], [0, 0, 1]]))
        poses.append(look_at(np.array([0.45 * np.cos(a), 0.45 * np.sin(a), 0.8]), np.array([0.0, 0.0, 0.05])))
        names.append(f"cam{i}")
    return names, K, poses


def synthetic(n_cams: int = 3, frames: int = 40, noise: float = 0.1, seed: int = 0, poses: list | None = None,
              dist: np.ndarray | None = None) -> tuple[Detections, list, list, list]:
    names, K, cams = rig(n_cams)
    dist = [np.array([-0.04, 0.01, 0.0005, -0.0005, 0.0]) if dist is None else dist for _ in range(n_cams)]
    boards = poses or calseq.sequence(BOARD, frames, seed)
    det = project_views(BOARD, names, [SIZE] * n_cams, K, dist, cams, boards, noise_px=noise, seed=seed)
    return det, K, dist, cams


def relative_errors(rig_cal, cams: list[np.ndarray]) -> list[tuple[float, float]]:
    """(mm, degrees) of each camera's pose relative to camera 0, against the truth: the rig's own
    geometry, free of the one-frame registration's error that every camera shares."""
    out = []
    ref_est, ref_true = np.linalg.inv(rig_cal.cameras[0].world_T_cam), np.linalg.inv(cams[0])
    for cam, truth in zip(rig_cal.cameras[1:], cams[1:], strict=True):
        est, tru = ref_est @ cam.world_T_cam, ref_true @ truth
        out.append((1000 * np.linalg.norm(est[:3, 3] - tru[:3, 3]), rotation_deg(est[:3, :3], tru[:3, :3])))
    return out


def test_pipeline_recovers_synthetic_truth():
    det, K, dist, cams = synthetic()
    cal = calibrate(det, BOARD, calseq.registration_pose(BOARD))
    errs = truth_errors(cal.rig, {n: (K[i], cams[i]) for i, n in enumerate(det.names)})
    for name, e in errs.items():
        assert e["focal_pct"] < 0.3, (name, e)
        assert e["principal_point_px"] < 1.5, (name, e)
        assert e["position_mm"] < 5.0, (name, e)  # the world frame rests on one registration frame set
        assert e["rotation_deg"] < 0.3, (name, e)
    for mm, deg in relative_errors(cal.rig, cams):
        assert mm < 1.0 and deg < 0.1, (mm, deg)
    for cam, d in zip(cal.rig.cameras, dist, strict=True):
        assert 0.05 < cam.rms_px < 0.2  # noise is 0.1 px per axis: RMS of the 2-D error ~0.14
        assert np.allclose(cam.dist[:2], d[:2], atol=0.02)
    # the file round-trips through the shared format
    again = from_json(to_json(cal.rig))
    assert np.allclose(again.cameras[1].world_T_cam, cal.rig.cameras[1].world_T_cam)
    again.check_rig({n: SIZE for n in det.names})


def test_gross_outliers_are_rejected():
    det, K, _, cams = synthetic(seed=1)
    rng = np.random.default_rng(3)
    hit = rng.choice(len(det.views), 12, replace=False)
    for i in hit:  # one corner per chosen view moved by 5-15 px
        det.views[i].corners[0] += rng.uniform(5, 15, 2) * rng.choice([-1, 1], 2)
    cal = calibrate(det, BOARD, calseq.registration_pose(BOARD))
    assert (~cal.bundle.inlier).sum() >= 12
    errs = truth_errors(cal.rig, {n: (K[i], cams[i]) for i, n in enumerate(det.names)})
    assert max(e["focal_pct"] for e in errs.values()) < 0.3
    assert max(mm for mm, _ in relative_errors(cal.rig, cams)) < 1.0
    assert max(c.rms_px for c in cal.rig.cameras) < 0.2


def test_camera_that_never_sees_the_board_is_named():
    det, *_ = synthetic()
    det.views = [v for v in det.views if v.camera != 2]
    with pytest.raises(CaptureUnusableError, match=r"cam2 never saw the board.*wave the board"):
        calibrate(det, BOARD, calseq.registration_pose(BOARD))


def test_camera_without_shared_views_is_named():
    det, *_ = synthetic(frames=60)
    # cam2 keeps only frame sets nobody else saw: it cannot be linked to the rig
    others = {v.frame for v in det.views if v.camera != 2}
    det.views = [v for v in det.views if v.camera != 2 or v.frame not in others]
    extra = [f for f in range(det.n_frames) if f not in others][:6]
    if len(extra) < 4:  # make frame sets seen by cam2 alone
        det.views = [v for v in det.views if v.camera != 2]
        donor = [v for v in det.views if v.camera == 0][:6]
        for i, v in enumerate(donor):
            det.views.append(type(v)(2, det.n_frames + i, v.ids, v.corners))
        det.n_frames += len(donor)
    with pytest.raises(CaptureUnusableError, match=r"cam2 share fewer than 3 frame sets"):
        calibrate(det, BOARD, calseq.registration_pose(BOARD))


def test_degenerate_views_are_skipped_and_counted():
    obj = BOARD.corners()
    ids = np.arange(len(obj))
    scale = 600.0
    flat = obj[:, :2] * scale + 20  # square-on, large
    assert degenerate(ids, flat, BOARD, SIZE) is None
    assert degenerate(ids[:4], flat[:4], BOARD, SIZE) == "too_few"
    row = ids[ids // (BOARD.squares_x - 1) == 0]
    assert degenerate(row, flat[row], BOARD, SIZE) == "collinear"
    assert degenerate(ids, obj[:, :2] * 40 + 100, BOARD, SIZE) == "too_small"
    edge_on = np.c_[flat[:, 0], 200 + obj[:, 1] * scale * 0.1]  # y squashed 10x: board seen ~84 degrees off-axis
    assert degenerate(ids, edge_on, BOARD, SIZE) == "edge_on"
    det = Detections(["a"], [SIZE], 3)
    add_view(det, 0, 0, (ids, edge_on), BOARD)
    add_view(det, 0, 1, None, BOARD)
    add_view(det, 0, 2, (ids, flat), BOARD)
    assert len(det.views) == 1
    assert det.skipped_by_camera() == {"a": {"edge_on": 1, "not_seen": 1}}


def test_edge_on_poses_in_a_capture_are_counted_not_used():
    names, K, cams = rig(3)
    reg = calseq.registration_pose(BOARD)
    # a board whose print faces 85 degrees away from the direction to cam0: edge-on for cam0
    centre = np.array([0.0, 0.0, 0.2])
    d = cams[0][:3, 3] - centre
    d /= np.linalg.norm(d)
    perp = np.cross(d, [0.0, 1.0, 0.0])
    perp /= np.linalg.norm(perp)
    normal = np.cos(np.radians(85)) * d + np.sin(np.radians(85)) * perp
    x_axis = np.array([0.0, 1.0, 0.0])
    z_axis = -normal  # the print faces -z of the board frame
    tilted = calseq.board_pose(BOARD, centre, np.c_[x_axis, np.cross(z_axis, x_axis), z_axis])
    det = project_views(BOARD, names, [SIZE] * 3, K, [np.zeros(5)] * 3, cams, [reg, tilted], noise_px=0.0)
    assert [v.frame for v in det.views if v.camera == 0] == [0]
    assert det.skipped[(0, "edge_on")] == 1


def test_robust_pose_average_ignores_a_wrong_sample():
    base = calseq.registration_pose(BOARD)
    rng = np.random.default_rng(0)
    samples = []
    for _ in range(7):
        T = base.copy()
        T[:3, :3] = calseq.Rotation.from_rotvec(rng.normal(0, 1e-3, 3)).as_matrix() @ T[:3, :3]
        T[:3, 3] += rng.normal(0, 1e-4, 3)
        samples.append(T)
    wrong = base.copy()
    wrong[:3, 3] += [0.1, 0, 0]
    avg = average_pose(samples + [wrong])
    assert np.linalg.norm(avg[:3, 3] - base[:3, 3]) < 1e-3


def test_sequence_starts_with_the_registration_board_face_up_on_the_table():
    reg = calseq.Registration(xy=(0.1, -0.05), yaw_deg=30.0, thickness_m=0.004)
    poses = calseq.sequence(BOARD, 20, seed=5, reg=reg)
    assert len(poses) == 20
    corners = BOARD.corners() @ poses[0][:3, :3].T + poses[0][:3, 3]
    assert np.allclose(corners[:, 2], 0.004)
    assert np.allclose(corners.mean(axis=0)[:2], [0.1, -0.05], atol=1e-9)
    assert np.allclose(poses[0][:3, :3] @ [0, 0, -1.0], [0, 0, 1])  # the print faces up
    again = calseq.sequence(BOARD, 20, seed=5, reg=reg)
    assert all(np.allclose(a, b) for a, b in zip(poses, again, strict=True))
    for T in poses[1:]:
        normal = T[:3, :3] @ [0, 0, -1.0]
        assert normal[2] >= np.cos(np.radians(calseq.MAX_TILT_DEG)) - 1e-9
        assert calseq.VOLUME_Z[0] <= (T @ [*np.array(BOARD.size_m) / 2, 0, 1])[2] <= calseq.VOLUME_Z[1]


def test_board_and_settings_reject_bad_geometry():
    with pytest.raises(BoardError, match="smaller than the square"):
        BoardSpec(marker_m=0.06)
    with pytest.raises(BoardError, match="unknown ArUco dictionary"):
        BoardSpec(dictionary="DICT_9X9_1")
    with pytest.raises(BoardError, match="needs 60"):
        BoardSpec(squares_x=12, squares_y=10, dictionary="DICT_4X4_50")
    with pytest.raises(BoardError, match="unknown key"):
        settings_from_table({"board": {"square": 0.05}})
    with pytest.raises(BoardError, match="unknown key"):
        settings_from_table({"boards": {}})
    s = settings_from_table({"board": {"squares_x": 9, "square_m": 0.03, "marker_m": 0.022}, "width": 320})
    assert (s.board.squares_x, s.board.square_m, s.width, s.height) == (9, 0.03, 320, 480)


def test_centred_model_keeps_the_principal_point_at_the_image_centre():
    det, K, _, cams = synthetic(dist=np.array([-0.04, 0.01, 0.0, 0.0, 0.0]))
    cal = calibrate(det, BOARD, calseq.registration_pose(BOARD), model="centred")
    for cam, k in zip(cal.rig.cameras, K, strict=True):
        assert np.allclose(cam.K[:2, 2], [(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2])
        assert cam.K[0, 0] == cam.K[1, 1]
        assert np.allclose(cam.dist[2:], 0.0)
        assert abs(cam.K[0, 0] / k[0, 0] - 1) < 0.01  # the truth's off-centre point costs some focal accuracy


def test_the_world_model_carries_a_textured_board_that_touches_nothing():
    m = build_model()
    body = m.body(CALIB_BOARD)
    assert m.body_mocapid[body.id] >= 0
    geoms = range(m.body_geomadr[body.id], m.body_geomadr[body.id] + m.body_geomnum[body.id])
    assert all(m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0 for g in geoms)
    assert any(m.geom_matid[g] >= 0 for g in geoms)  # the printed texture survived the compile
    others = [g for g in range(m.ngeom) if m.geom_bodyid[g] != body.id and m.geom_contype[g] == 0
              and m.geom_conaffinity[g] == 0]
    assert others and all(m.geom_rgba[g][3] == 0 for g in others)  # visual-only geoms stay out of the images
    img = BOARD.image(96)
    assert m.tex_width[0] * m.tex_height[0] == img.size


def test_missing_registration_board_is_named():
    det, *_ = synthetic()
    det.views = [v for v in det.views if v.frame != 0]
    with pytest.raises(CaptureUnusableError, match=r"registration board \(frame set 0\)"):
        calibrate(det, BOARD, calseq.registration_pose(BOARD))
