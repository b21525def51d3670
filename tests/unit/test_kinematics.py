"""URDF parsing and forward kinematics: numpy vs CasADi vs MuJoCo, mimic coupling, bad input."""

from __future__ import annotations

import casadi as ca
import mujoco
import numpy as np
import pytest

from shared.kinematics import ROBOTS_DIR, URDFError, load_robot, parse_urdf


def random_q(model, rng):
    lo = np.where(np.isfinite(model.lower), model.lower, -np.pi)
    hi = np.where(np.isfinite(model.upper), model.upper, np.pi)
    return rng.uniform(lo, hi)


@pytest.mark.parametrize("name", ["workcell", "hand_arm"])
def test_numpy_and_casadi_fk_agree(name):
    model = load_robot(name)
    rng = np.random.default_rng(1)
    q_sym = ca.SX.sym("q", len(model.joint_names))
    sym = model.fk_casadi(q_sym)
    frames = list(model.keypoints) + [j.child for j in model.moving]
    f = ca.Function("f", [q_sym], [v for fr in frames for v in sym[fr]])
    for _ in range(5):
        q = random_q(model, rng)
        poses = model.fk(q)
        out = f(q)
        for i, fr in enumerate(frames):
            np.testing.assert_allclose(np.array(out[2 * i]), poses[fr][:3, :3], atol=1e-12)
            np.testing.assert_allclose(np.array(out[2 * i + 1]).ravel(), poses[fr][:3, 3], atol=1e-12)


@pytest.mark.parametrize("name", ["workcell", "hand_arm"])
def test_fk_matches_mujoco_bodies(name):
    model = load_robot(name)
    m = mujoco.MjModel.from_xml_path(str(ROBOTS_DIR / f"{name}.urdf"))
    d = mujoco.MjData(m)
    rng = np.random.default_rng(2)
    for _ in range(4):
        q = model.couple(random_q(model, rng))  # MuJoCo only enforces mimic equalities in dynamics
        for jn, v in zip(model.joint_names, q, strict=True):
            d.qpos[m.jnt_qposadr[m.joint(jn).id]] = v
        mujoco.mj_kinematics(m, d)
        poses = model.fk(q)
        for link in [j.child for j in model.joints]:
            bid = m.body(link).id
            np.testing.assert_allclose(d.xpos[bid], poses[link][:3, 3], atol=1e-6, err_msg=link)
            np.testing.assert_allclose(d.xmat[bid].reshape(3, 3), poses[link][:3, :3], atol=1e-6, err_msg=link)


def test_mimic_joint_follows_its_master():
    model = load_robot("workcell")
    q = np.zeros(10)
    q[model.joint_names.index("left_finger_a")] = 0.03
    q[model.joint_names.index("left_finger_b")] = 0.0  # ignored: coupled to finger_a
    poses = model.fk(q)
    gap = poses["left_tip_a"][1, 3] - poses["left_tip_b"][1, 3]
    assert gap == pytest.approx(2 * 0.03 + 2 * 0.002)
    assert model.couple(q)[model.joint_names.index("left_finger_b")] == pytest.approx(0.03)
    hand = load_robot("hand_arm")
    names = hand.joint_names
    qh = np.zeros(len(names))
    qh[names.index("index_j2")] = 0.7
    assert hand.couple(qh)[names.index("index_j3")] == pytest.approx(0.7)
    assert len(hand.actuated) == len(names) - 4  # four coupled distal joints


def test_prismatic_joints_move_the_tips_along_world_axes():
    model = load_robot("workcell")
    q = np.zeros(10)
    n = model.joint_names
    q[n.index("right_x")], q[n.index("right_y")], q[n.index("right_z")] = 0.1, -0.05, 0.05
    tip = model.fk(q)["right_tip"][:3, 3]
    np.testing.assert_allclose(tip, [0.1 + 0.02, -0.15 - 0.05, 0.26 - 0.05], atol=1e-12)  # y from home -0.15
    q[n.index("right_wrist")] = np.pi / 2  # the finger is off the wrist axis: it swings round
    np.testing.assert_allclose(model.fk(q)["right_tip"][:3, 3], [0.1, -0.2 + 0.02, 0.21], atol=1e-12)


def test_rpy_origin_and_continuous_joint(tmp_path):
    urdf = tmp_path / "r.urdf"
    urdf.write_text("""<robot name="r"><link name="a"/><link name="b"/><link name="c"/>
      <joint name="j" type="continuous"><parent link="a"/><child link="b"/>
        <origin xyz="1 0 0" rpy="0 0 1.5707963267948966"/><axis xyz="0 0 1"/></joint>
      <joint name="f" type="fixed"><parent link="b"/><child link="c"/><origin xyz="1 0 0"/></joint></robot>""")
    model = parse_urdf(urdf)
    assert model.joint_names == ["j"] and model.keypoints == ["c"] and np.isinf(model.upper[0])
    np.testing.assert_allclose(model.fk(np.array([0.0]))["c"][:3, 3], [1, 1, 0], atol=1e-12)
    np.testing.assert_allclose(model.fk(np.array([np.pi / 2]))["c"][:3, 3], [0, 0, 0], atol=1e-12)


@pytest.mark.parametrize("body, message", [
    ('<joint name="j" type="planar"><parent link="a"/><child link="b"/></joint>', "not supported"),
    ('<joint name="j" type="revolute"><parent link="a"/><child link="b"/><origin xyz="1 0"/></joint>', "xyz"),
    ('<joint name="j" type="prismatic"><parent link="a"/><child link="b"/>'
     '<limit lower="1" upper="0" velocity="1" effort="1"/></joint>', "lower limit"),
    ('<joint name="j" type="revolute"><parent link="a"/><child link="b"/><mimic joint="nope"/></joint>', "mimics"),
])
def test_bad_urdf_raises_a_specific_error(tmp_path, body, message):
    urdf = tmp_path / "bad.urdf"
    urdf.write_text(f'<robot name="bad"><link name="a"/><link name="b"/>{body}</robot>')
    with pytest.raises(URDFError, match=message):
        parse_urdf(urdf)


def test_fk_rejects_a_wrong_length_q():
    with pytest.raises(ValueError, match="shape"):
        load_robot("workcell").fk(np.zeros(9))
