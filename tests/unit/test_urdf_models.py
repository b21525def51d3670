"""The project's robot models: generated files up to date, joint layout, limits, MuJoCo loads them."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from shared.kinematics import ROBOTS_DIR, load_robot
from shared.robots import make_hand_arm_urdf, make_workcell_urdf
from shared.robots.urdf_writer import frustum, read_stl

JOINTS = ["left_x", "left_y", "left_z", "left_wrist", "left_finger_a", "left_finger_b",
          "right_x", "right_y", "right_z", "right_wrist"]


def test_checked_in_urdfs_match_their_generators():
    assert (ROBOTS_DIR / "workcell.urdf").read_text() == make_workcell_urdf.urdf()
    assert (ROBOTS_DIR / "hand_arm.urdf").read_text() == make_hand_arm_urdf.urdf()
    v, _ = frustum(bottom=(0.05, 0.09), top=(0.06, 0.06), height=make_workcell_urdf.HEAD_HEIGHT)
    np.testing.assert_allclose(read_stl(ROBOTS_DIR / make_workcell_urdf.GRIPPER_MESH),
                               np.unique(np.round(v, 7), axis=0), atol=1e-6)


def test_workcell_layout_limits_and_keypoints():
    model = load_robot("workcell")
    assert model.joint_names == JOINTS
    assert [j.name for j in model.actuated] == [n for n in JOINTS if n != "left_finger_b"]
    assert set(model.keypoints) == {"left_wrist_point", "left_tip_a", "left_tip_b", "right_wrist_point", "right_tip"}
    lim = dict(zip(JOINTS, zip(model.lower, model.upper, model.max_velocity, strict=True), strict=True))
    assert lim["left_y"][:2] == (-0.2, 0.2) and lim["right_y"][:2] == (-0.2, 0.2)  # from home y = +-0.15
    assert lim["left_x"][:2] == (-0.3, 0.3) and lim["left_finger_a"][:2] == (0.0, 0.04)
    assert lim["left_x"][2] == 0.5 and lim["left_wrist"][2] == 6.0 and lim["left_finger_a"][2] == 0.2
    kinds = {s.kind for s in model.shapes}
    assert {"box", "cylinder", "sphere", "mesh"} <= kinds
    mesh = next(s for s in model.shapes if s.kind == "mesh")
    assert mesh.vertices.shape == (8, 3)
    # the reach: tips 26 cm above the table at the top, 1 cm at the bottom, inside the 0.8 m frame
    q = np.zeros(10)
    home = model.fk(q)
    assert home["right_tip"][2, 3] == pytest.approx(0.26)
    assert home["left_carriage"][1, 3] - home["right_carriage"][1, 3] == pytest.approx(0.3)  # safe home
    q[[2, 8]] = model.upper[[2, 8]]
    q[[0, 1, 6, 7]] = [0.3, 0.2, -0.3, -0.2]
    poses = model.fk(q)
    assert poses["left_tip_a"][2, 3] == pytest.approx(0.01)
    assert poses["left_carriage"][1, 3] == pytest.approx(0.35) and poses["right_carriage"][1, 3] == pytest.approx(-0.35)
    q[[1, 7]] = -0.2, 0.2  # both carriages towards the middle: they overlap (the optimizer's job)
    poses = model.fk(q)
    assert poses["left_carriage"][1, 3] == pytest.approx(-0.05) and poses["right_carriage"][1, 3] == pytest.approx(0.05)
    assert all(abs(poses[k][0, 3]) < 0.4 and abs(poses[k][1, 3]) < 0.4 for k in model.keypoints)


@pytest.mark.parametrize("name", ["workcell", "hand_arm"])
def test_mujoco_loads_the_model_with_valid_inertias_and_limits(name):
    m = mujoco.MjModel.from_xml_path(str(ROBOTS_DIR / f"{name}.urdf"))
    model = load_robot(name)
    assert m.njnt == len(model.joint_names)
    for jn, lo, hi in zip(model.joint_names, model.lower, model.upper, strict=True):
        j = m.joint(jn)
        assert j.limited[0] and np.allclose(j.range, [lo, hi])
    assert m.neq == len(model.joint_names) - len(model.actuated)  # one equality per mimic joint
    d = mujoco.MjData(m)
    for _ in range(200):
        mujoco.mj_step(m, d)
    assert np.isfinite(d.qpos).all()


def test_hand_arm_has_coupled_fingers_and_tip_keypoints():
    model = load_robot("hand_arm")
    assert len([j for j in model.moving if not j.name.startswith(("shoulder", "elbow", "wrist"))]) == 13
    assert {j.name: j.mimic for j in model.moving if j.mimic} == {f"{f}_j3": f"{f}_j2"
                                                                 for f in ("thumb", "index", "middle", "ring")}
    assert set(model.keypoints) == {"wrist_point", "thumb_tip", "index_tip", "middle_tip", "ring_tip"}
    assert {s.kind for s in model.shapes} <= {"box", "cylinder", "sphere"}
    # flexing a finger moves its tip towards the palm side (-y of the palm)
    q = np.zeros(len(model.joint_names))
    palm = model.fk(q)["palm"]
    q2 = q.copy()
    q2[model.joint_names.index("index_j2")] = 1.0
    d = model.fk(q2)["index_tip"][:3, 3] - model.fk(q)["index_tip"][:3, 3]
    assert palm[:3, 1] @ d < -0.01
