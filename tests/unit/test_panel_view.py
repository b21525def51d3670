"""The dashboard's pure conversions: hands, tactile heatmaps, camera poses, plans, robot boxes, tables."""

from __future__ import annotations

import numpy as np
import pytest

from services.panel import view
from shared.geometry import look_at, projection
from shared.kinematics import load_robot


def test_bones_form_the_openpose_hand_tree():
    assert len(view.BONES) == 20
    parents = {child: parent for parent, child in view.BONES}
    assert sorted(parents) == list(range(1, 21)), "every keypoint but the wrist has exactly one parent"
    for tip in (4, 8, 12, 16, 20):  # fingertips are leaves, four bones from the wrist
        assert tip not in {p for p, _ in view.BONES}
        k, depth = tip, 0
        while k != 0:
            k, depth = parents[k], depth + 1
        assert depth == 4


def test_hand_segments_dim_bones_with_an_unobserved_end():
    hand = np.arange(63, dtype=float).reshape(21, 3)
    mask = np.ones(21, bool)
    mask[8] = False  # index fingertip occluded
    seg, bright = view.hand_segments(hand, mask)
    assert seg.shape == (20, 2, 3)
    i = view.BONES.index((7, 8))
    np.testing.assert_array_equal(seg[i], hand[[7, 8]])
    assert bright[i] == view.DIM
    assert np.all(np.delete(bright, i) == 1.0)
    colors = view.segment_colors((200, 100, 50), bright)
    assert colors.shape == (20, 2, 3) and colors.dtype == np.uint8
    assert tuple(colors[i, 0]) == (70, 35, 18) and tuple(colors[0, 1]) == (200, 100, 50)


def test_hand_arrays_reshape_and_reject_wrong_sizes():
    flat = np.random.default_rng(0).normal(size=2 * 21 * 3)
    hands, mask = view.hand_arrays(flat, [], 2)
    assert hands.shape == (2, 21, 3) and mask.all()
    np.testing.assert_allclose(hands[1, 0], flat[63:66])
    with pytest.raises(view.ViewError, match="hand_keypoints"):
        view.hand_arrays(flat[:-3], [], 2)
    with pytest.raises(view.ViewError, match="hand_mask"):
        view.hand_arrays(flat, [1] * 21, 2)


def test_tactile_image_maps_pressure_to_brightness_and_greys_missing_cells():
    pressure = np.zeros(256)
    pressure[0] = 30.0  # saturated cell at row 0, col 0
    pressure[17] = 10.0  # row 1, col 1
    mask = np.ones(256, np.uint8)
    mask[255] = 0
    img = view.tactile_image(pressure, mask, scale=4)
    assert img.shape == (64, 64, 3) and img.dtype == np.uint8
    hot, warm, cold = img[0, 0].astype(int).sum(), img[4, 4].astype(int).sum(), img[0, 8].astype(int).sum()
    assert hot > warm > cold
    assert tuple(img[63, 63]) == (40, 40, 40)
    assert np.array_equal(img[0:4, 0:4], np.broadcast_to(img[0, 0], (4, 4, 3))), "each cell is a scale x scale block"
    with pytest.raises(view.ViewError, match="16x16"):
        view.tactile_image(np.zeros(100))


def test_tactile_mesh_arrays_split_hands_and_reject_inconsistent_sizes():
    verts = np.arange(2 * 4 * 3, dtype=np.float32)
    faces = np.array([0, 1, 2, 0, 2, 3, 0, 2, 1, 0, 3, 2])  # two triangles per hand
    hands = view.tactile_mesh_arrays(["left", "right"], 4, verts, faces, np.arange(8.0))
    assert [h[0] for h in hands] == ["left", "right"]
    name, v, f, p = hands[1]
    np.testing.assert_array_equal(v, verts.reshape(2, 4, 3)[1])
    np.testing.assert_array_equal(f, [[0, 2, 1], [0, 3, 2]])
    np.testing.assert_array_equal(p, [4, 5, 6, 7])
    assert view.tactile_mesh_arrays([], 4, [], [], []) == []
    for args, words in (((verts[:-3], faces, np.arange(8.0)), "vertex values"),
                        ((verts, faces[:-1], np.arange(8.0)), "face indices"),
                        ((verts, np.where(faces == 3, 4, faces), np.arange(8.0)), "outside"),
                        ((verts, faces, np.arange(7.0)), "pressures"),
                        ((verts, faces, np.arange(8.0), [1, 0, 1]), "sensed flags")):
        with pytest.raises(view.ViewError, match=words):
            view.tactile_mesh_arrays(["left", "right"], 4, *args)


def test_tactile_mesh_colors_heat_the_sensed_vertices_only():
    base = view.HAND_COLORS["right"]
    rgb = view.tactile_mesh_colors([0.0, 30.0, 30.0, np.nan], [1, 1, 0, 1], base)
    assert rgb.dtype == np.uint8 and rgb.shape == (4, 3)
    assert rgb[0].sum() < 30 and rgb[1].sum() > 600, "inferno: black at 0 kPa, near white at 30"
    assert tuple(rgb[2]) == base, "unsensed vertices keep the hand's colour"
    np.testing.assert_array_equal(rgb[3], rgb[0])  # NaN reads as 0
    with pytest.raises(view.ViewError, match="sensed flags"):
        view.tactile_mesh_colors([1.0, 2.0], [1], base)


def test_palm_side_view_faces_the_sensors():
    verts = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.0, 0.1], [0.1, 0.0, 0.1],
                      [0.05, 0.02, 0.05], [0.05, 0.02, 0.05]]) + [0.2, 0.1, 0.3]  # sensors toward +y
    position, target = view.palm_side_view(verts, [0, 0, 0, 0, 1, 1], distance=0.4)
    np.testing.assert_allclose(target, verts.mean(axis=0))
    np.testing.assert_allclose(position - target, [0.0, 0.4, 0.0], atol=1e-9)
    down = np.array([[0.0, 0.0, 0.3], [0.1, 0.0, 0.3], [0.0, 0.1, 0.3], [0.1, 0.1, 0.3],
                     [0.05, 0.05, 0.28], [0.05, 0.05, 0.28]])  # flat, palm down: from below at 45 degrees
    position, target = view.palm_side_view(down, [0, 0, 0, 0, 1, 1], distance=0.4)
    np.testing.assert_allclose(position - target, 0.4 * np.array([0.5, -0.5, -np.sqrt(0.5)]), atol=1e-9)


def test_camera_frustum_recovers_the_pose_and_fov_from_projection():
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    world_T_cam = look_at(np.array([0.4, -0.4, 0.8]), np.array([0.03, 0.0, 0.02]))
    P = projection(K, world_T_cam)
    f = view.camera_frustum(P.ravel(), 320, 240)
    np.testing.assert_allclose(f.position, [0.4, -0.4, 0.8], atol=1e-6)
    assert f.fov == pytest.approx(2 * np.arctan(120 / 300))
    assert f.aspect == pytest.approx(320 / 240)
    w, x, y, z = f.wxyz  # rotation back from the quaternion equals the camera's axes
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    np.testing.assert_allclose(R, world_T_cam[:3, :3], atol=1e-6)
    with pytest.raises(view.ViewError, match="K\\[R\\|t\\]"):
        view.camera_frustum(np.zeros(12), 320, 240)


def test_plan_segments_join_consecutive_valid_steps_only():
    steps, points = 3, 2
    pos = np.arange(steps * points * 3, dtype=float)
    mask = np.ones((steps, points), np.uint8)
    mask[1, 1] = 0  # point 1 missing at step 1: neither of its segments is drawn
    seg = view.plan_segments(pos, mask.ravel(), steps, points)
    assert seg.shape == (2, 2, 3)
    p = pos.reshape(steps, points, 3)
    np.testing.assert_array_equal(seg[0], p[[0, 1], 0])
    np.testing.assert_array_equal(seg[1], p[[1, 2], 0])
    assert view.plan_segments(pos, [], steps, points).shape == (4, 2, 3)
    assert view.plan_segments([], [], 0, 0).shape == (0, 2, 3)
    with pytest.raises(view.ViewError):
        view.plan_segments(pos[:-1], [], steps, points)


def test_joint_vector_reorders_by_name():
    q = view.joint_vector(["a", "b", "c"], ["c", "a"], [3.0, 1.0])
    np.testing.assert_array_equal(q, [1.0, 0.0, 3.0])


def test_link_boxes_follow_forward_kinematics():
    robot = load_robot("workcell")
    q0 = np.zeros(len(robot.joint_names))
    boxes = {b.name: b for b in view.link_boxes(robot, q0)}
    assert len(boxes) == len(robot.shapes)
    for i, s in enumerate(robot.shapes):
        b = boxes[f"{s.link}_{i}"]
        assert b.dimensions.shape == (3,) and np.all(b.dimensions > 0)
        if s.kind == "mesh":  # the mesh's own bounding box, not its scale
            np.testing.assert_allclose(b.dimensions, s.vertices.max(0) - s.vertices.min(0))
    q1 = q0.copy()
    q1[robot.joint_names.index("left_y")] = 0.1  # moves the carriage along the rail
    moved = {b.name: b for b in view.link_boxes(robot, q1)}
    carriage = next(n for n in boxes if n.startswith("left_carriage"))
    rail = next(n for n in boxes if n.startswith("y_rail"))
    assert np.linalg.norm(moved[carriage].pose[:3, 3] - boxes[carriage].pose[:3, 3]) == pytest.approx(0.1)
    np.testing.assert_allclose(moved[rail].pose, boxes[rail].pose)


def test_link_boxes_draw_the_hand_arm_with_coupled_fingers():
    """The panel draws whichever model the deployment names: the hand-arm's cylinders and spheres get
    boxes, and a state that leaves out the coupled distal joints still bends them with their master."""
    robot = load_robot("hand_arm")
    names = robot.joint_names
    q = view.joint_vector(names, ["index_j2"], [1.0])  # index_j3 missing from the message
    boxes = {b.name: b for b in view.link_boxes(robot, q)}
    assert len(boxes) == len(robot.shapes)
    straight = {b.name: b for b in view.link_boxes(robot, np.zeros(len(names)))}
    i = next(i for i, s in enumerate(robot.shapes) if s.link == "index_distal")
    flexed, flat = boxes[f"index_distal_{i}"].pose, straight[f"index_distal_{i}"].pose
    # the distal bone turned by j2 + j3 (coupled) = 2 rad relative to the straight finger
    assert np.degrees(np.arccos(np.clip((np.trace(flat[:3, :3].T @ flexed[:3, :3]) - 1) / 2, -1, 1))) == \
        pytest.approx(np.degrees(2.0), abs=1e-6)


def test_joint_markers_bar_height_is_the_joint_magnitude():
    bars = view.joint_markers([0.2, -0.4, 0.0], gain=1.0)
    assert bars.shape == (3, 2, 3)
    np.testing.assert_allclose(bars[:, 1, 2] - bars[:, 0, 2], [0.2, 0.4, 0.005])


def test_object_colors_one_colour_per_object():
    names = ["cup/rim", "cup/handle", "box/corner"]
    c = view.object_colors(names, [1, 0, 1])
    assert c.shape == (3, 3)
    assert tuple(c[0]) != tuple(c[2])
    np.testing.assert_array_equal(c[1], np.round(c[0] * view.DIM))


def test_health_table_rows_sorted_with_rates_and_errors():
    reports = [
        {"service": "robot", "instance": "workcell", "status": "ok", "pid": 12, "uptime_s": 5.4,
         "published_hz": {"xm/robot/workcell/state": 100.0, "xm/camhub/cam0/image": 4.0,
                                                "xm/camhub/cam1/image": 6.0},
         "received_hz": {"xm/a": 1.0}, "errors": {}},
        {"service": "glove", "instance": "left", "status": "error", "message": "port | gone", "pid": 11,
         "uptime_s": 3, "published_hz": {}, "errors": {"malformed:xm/x": 2}},
    ]
    table = view.health_table(reports).splitlines()
    assert len(table) == 4
    assert table[2].startswith("| glove/left | error: port / gone | 11 | 3 |") and "malformed:xm/x 2" in table[2]
    assert table[3].startswith("| robot/workcell | ok | 12 | 5 | image 2x5, state 100 | 1 | - |")
    assert "no service" in view.health_table([])


def test_recorder_text_for_every_reply():
    assert "no recorder answered" in view.recorder_text("start", [])
    assert view.recorder_text("start", [{"ok": False, "error": "already recording"}]) == "**error**: already recording"
    assert view.recorder_text("start", [{"ok": True, "path": "/r/a.mcap"}]) == "recording to `/r/a.mcap`"
    text = view.recorder_text("stop", [{"ok": True, "path": "/r/a.mcap", "messages": {"k": 3, "j": 4},
                                        "bytes": 2_500_000}])
    assert text == "saved `/r/a.mcap`: 7 messages, 2.5 MB"


def test_trajectory_paths_follow_each_point_through_the_knots():
    robot = load_robot("workcell")
    frames = ["left_tip_a", "right_tip"]
    knots = [np.zeros(len(robot.joint_names)) for _ in range(3)]
    x = robot.joint_names.index("left_x")
    knots[1][x], knots[2][x] = 0.05, 0.10  # the left carriage moves 5 cm per knot along its axis
    names = list(robot.joint_names)
    paths = view.trajectory_paths(robot, frames, names, knots)
    assert paths.shape == (2, 3, 3)
    for k, q in enumerate(knots):  # each knot's points are the forward kinematics of that knot
        poses = robot.fk(q)
        assert np.allclose(paths[0, k], poses["left_tip_a"][:3, 3])
        assert np.allclose(paths[1, k], poses["right_tip"][:3, 3])
    assert np.linalg.norm(paths[0, 2] - paths[0, 0]) == pytest.approx(0.10, abs=1e-6)  # a prismatic axis
    assert np.allclose(paths[1, 0], paths[1, 2])  # the right arm stands still
    # a message naming joints in another order is reordered by name
    order = names[::-1]
    assert np.allclose(view.trajectory_paths(robot, frames, order, [q[::-1] for q in knots]), paths)
    seg = view.path_segments(paths)
    assert seg.shape == (4, 2, 3) and np.allclose(seg[1], paths[0, 1:3])


def test_trajectory_paths_refuse_bad_trajectories():
    robot = load_robot("workcell")
    names = list(robot.joint_names)
    with pytest.raises(view.ViewError, match="no such robot frames"):
        view.trajectory_paths(robot, ["nowhere"], names, [np.zeros(len(names))])
    with pytest.raises(view.ViewError, match="without points"):
        view.trajectory_paths(robot, ["right_tip"], names, [])
    with pytest.raises(view.ViewError, match="positions for"):
        view.trajectory_paths(robot, ["right_tip"], names, [np.zeros(3)])
