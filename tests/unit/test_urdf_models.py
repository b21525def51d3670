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
    assert set(model.keypoints) == {"left_wrist_point", "left_tip_a", "left_tip_b", "left_grip_axis",
                                    "right_wrist_point", "right_tip"}
    lim = dict(zip(JOINTS, zip(model.lower, model.upper, model.max_velocity, strict=True), strict=True))
    assert lim["left_y"][:2] == (-0.27, 0.2) and lim["right_y"][:2] == (-0.2, 0.27)  # from home y = +-0.15
    assert lim["left_x"][:2] == (-0.3, 0.3) and lim["left_finger_a"][:2] == (0.0, 0.04)
    assert lim["left_x"][2] == 0.5 and lim["left_wrist"][2] == 6.0 and lim["left_finger_a"][2] == 0.2
    kinds = {s.kind for s in model.shapes}
    assert {"box", "cylinder", "sphere", "mesh"} <= kinds
    mesh = next(s for s in model.shapes if s.kind == "mesh")
    assert mesh.vertices.shape == (8, 3)
    # the reach: tips 26 cm above the table at the top; at the bottom the finger ends 1 mm above the
    # table (the gripper's pad points 3 mm above the ends), all inside the 0.8 m frame
    q = np.zeros(10)
    home = model.fk(q)
    assert home["left_tip_a"][2, 3] == pytest.approx(0.263) and home["right_tip"][2, 3] == pytest.approx(0.26)
    assert home["left_carriage"][1, 3] - home["right_carriage"][1, 3] == pytest.approx(0.3)  # safe home
    q[[2, 8]] = model.upper[[2, 8]]
    q[[0, 1, 6, 7]] = [0.3, 0.2, -0.3, -0.2]
    poses = model.fk(q)
    assert poses["left_tip_a"][2, 3] == pytest.approx(0.004)
    assert poses["right_tip"][2, 3] == pytest.approx(0.001)
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


def test_world_builds_the_hand_arm_with_motors_equalities_and_matching_kinematics():
    """The world's MuJoCo model of the hand-arm (services/world/model.py, robot="hand_arm"): a motor per
    independent joint limited to the URDF effort, an equality per mimic joint, forward kinematics of
    every body and keypoint equal to shared/kinematics, and the coupling held under the board's control."""
    from services.robot.board_sim import BoardSim
    from services.world.sim import WorldSim
    from shared.protocols import robot_board as rb

    sim = WorldSim(robot="hand_arm")
    m, d, model = sim.model, sim.data, sim.robot
    assert sim.joint_names == model.joint_names
    motors = {m.actuator(i).name: m.actuator_ctrlrange[i][1] for i in range(m.nu)}
    assert motors == {j.name: j.effort for j in model.actuated}
    joints = [i for i in range(m.neq) if m.eq_type[i] == mujoco.mjtEq.mjEQ_JOINT]
    assert len(joints) == 4 and m.neq == 5  # the mimic couplings, and the connector's snap-fit weld
    assert m.eq_type[m.equality("connector_latch").id] == mujoco.mjtEq.mjEQ_WELD
    rng = np.random.default_rng(3)
    frames = [j.child for j in model.joints]  # links and keypoint frames
    for _ in range(3):
        q = model.couple(rng.uniform(model.lower, model.upper))
        d.qpos[sim._qadr] = q
        mujoco.mj_kinematics(m, d)
        poses = model.fk(q)
        for f in frames:
            np.testing.assert_allclose(d.xpos[m.body(f).id], poses[f][:3, 3], atol=1e-9, err_msg=f)
            np.testing.assert_allclose(d.xmat[m.body(f).id].reshape(3, 3), poses[f][:3, :3], atol=1e-9, err_msg=f)
    # From the home pose, the board flexes the fingers; every distal joint follows its middle joint.
    sim.reset(0)
    sim.set_robot_mode("robot")
    names, n = sim.joint_names, len(sim.joint_names)
    q0, _ = sim.joint_state()
    assert model.fk(q0)["wrist_point"][2, 3] > 0.1  # the home pose stands over the table
    target = q0.copy()
    for finger in ("thumb", "index", "middle", "ring"):
        target[names.index(f"{finger}_j2")] = target[names.index(f"{finger}_j3")] = 0.8
    target[names.index("elbow")] -= 0.2
    board = BoardSim(names)
    cmd = rb.CommandFrame(0, np.full(n, rb.Mode.POSITION, np.uint8), target, *np.zeros((4, n)))
    for step in range(1000):
        if step % 4 == 0:
            board.receive(cmd, sim.time)
        q, qd = sim.joint_state()
        sim.set_efforts(board.step(sim.time, q, qd, sim.physics_dt)[0])
        sim.step(1)
    q, _ = sim.joint_state()
    np.testing.assert_allclose(q, target, atol=5e-3)
    for finger in ("thumb", "index", "middle", "ring"):
        assert q[names.index(f"{finger}_j3")] == pytest.approx(q[names.index(f"{finger}_j2")], abs=1e-3)
