"""Robot descriptions (shared/robots): each agrees with its URDF, the registry refuses unknown names,
and the URDF loaded through yourdfpy/trimesh gives the forward kinematics recorded for these models."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.trajopt.mapping import PlanArrays, with_derived_point
from services.trajopt.optimizer import default_pairs, default_point_map
from shared.kinematics import URDFError, load_robot, parse_urdf
from shared.robots.registry import DEFAULT_ROBOT, REGISTRY, UnknownRobotError, describe

# Keypoint positions (m) recorded from the models at q = lower + f * (upper - lower), limits clipped
# to +-3, mimic joints coupled; f = None is the zero pose.
FK = {
    "workcell": {
        None: {"left_wrist_point": [0.0, 0.15, 0.34], "left_grip_axis": [0.0, 0.12, 0.263],
               "left_tip_a": [0.0, 0.152, 0.263], "left_tip_b": [0.0, 0.148, 0.263],
               "right_wrist_point": [0.0, -0.15, 0.34], "right_tip": [0.02, -0.15, 0.26]},
        0.3: {"left_wrist_point": [-0.12, 0.021, 0.2623],
              "left_grip_axis": [-0.14796117257901678, 0.010129267365699789, 0.1853],
              "left_tip_a": [-0.10695145279645882, 0.026073008562673416, 0.1853],
              "left_tip_b": [-0.13304854720354117, 0.015926991437326565, 0.1853],
              "right_wrist_point": [-0.12, -0.209, 0.2623],
              "right_tip": [-0.11275284491046653, -0.22764078171934451, 0.1823]},
        0.8: {"left_wrist_point": [0.18, 0.256, 0.1328],
              "left_grip_axis": [0.20921542892634584, 0.2628160628407926, 0.0558],
              "left_tip_a": [0.14688918055014136, 0.24827512878043503, 0.0558],
              "left_tip_b": [0.21311081944985863, 0.263724871219565, 0.0558],
              "right_wrist_point": [0.18, 0.026, 0.1328],
              "right_tip": [0.17545595810613823, 0.04547695261756395, 0.0528]},
    },
    "hand_arm": {
        None: {"wrist_point": [-0.2369999999984011, -0.5000008705496094, 1.428],
               "thumb_tip": [-0.3412465430626106, -0.39075490508256167, 1.4459996170826614],
               "index_tip": [-0.43700011019185575, -0.4700016051908324, 1.4279992653589795],
               "middle_tip": [-0.4409999999956486, -0.5000016198834505, 1.427999250666159],
               "ring_tip": [-0.43699988979954946, -0.5300016051904277, 1.4279992653589795]},
        0.3: {"wrist_point": [-0.9952740467093384, -0.688764177462062, -0.19328472127432425],
              "thumb_tip": [-1.0533227861061594, -0.624067876986828, -0.3067314355872067],
              "index_tip": [-1.1363690289529405, -0.6335426982943247, -0.2965961611096009],
              "middle_tip": [-1.1509747094291818, -0.6267952952565599, -0.27096128935115626],
              "ring_tip": [-1.1581798755796693, -0.6202809057616568, -0.24229688092794668]},
        0.8: {"wrist_point": [-0.19621500619010296, -0.6858101204683829, -0.5347696404573679],
              "thumb_tip": [-0.21281306157916557, -0.7350026348818188, -0.5504125510775995],
              "index_tip": [-0.1787374647018925, -0.6985990397839348, -0.6200189500316906],
              "middle_tip": [-0.15129316487783612, -0.6980789207619739, -0.6072698369891966],
              "ring_tip": [-0.12789108626243476, -0.7003683403882255, -0.5882146205313993]},
    },
}


@pytest.mark.parametrize("name", sorted(FK))
def test_loaded_models_give_the_recorded_forward_kinematics(name):
    model = load_robot(name)
    lo, hi = np.clip(model.lower, -3, 3), np.clip(model.upper, -3, 3)
    for f, points in FK[name].items():
        q = np.zeros(len(model.joint_names)) if f is None else model.couple(lo + f * (hi - lo))
        poses = model.fk(q)
        assert model.keypoints == list(points)
        for frame, p in points.items():
            np.testing.assert_allclose(poses[frame][:3, 3], p, rtol=0, atol=1e-12, err_msg=f"{name} {f} {frame}")


@pytest.mark.parametrize("name", sorted(REGISTRY))
def test_every_description_agrees_with_its_urdf(name):
    desc, model = describe(name), load_robot(name)
    assert desc.problems(model.joint_names, model.frames(), model.links) == []
    assert list(desc.joints) == model.joint_names == desc.board_order
    assert default_point_map(model) == desc.point_map
    assert default_pairs(model) == list(desc.collision_pairs)
    assert set(desc.sim_motors) == {j.name for j in model.actuated}


def test_a_description_that_disagrees_with_its_urdf_is_named():
    desc, model = describe("hand_arm"), load_robot("hand_arm")
    bad = dataclasses.replace(desc, joints=desc.joints[::-1], point_map={"right/4": "thumb_nail"},
                              board_channels={j: 2 * i for i, j in enumerate(desc.joints)}, home={"knee": 1.0})
    problems = " | ".join(bad.problems(model.joint_names, model.frames(), model.links))
    for part in ("differ from the URDF", "board channels", "thumb_nail: no such frame", "knee: not a moving joint"):
        assert part in problems


def test_unknown_robots_are_refused_with_the_known_names():
    with pytest.raises(UnknownRobotError, match="known: workcell, hand_arm"):
        describe("no_such")
    with pytest.raises(FileNotFoundError, match="no robot model 'no_such'"):
        load_robot("no_such")
    assert DEFAULT_ROBOT in REGISTRY


def test_grasp_roles_name_the_executed_points_and_joints():
    g = describe(DEFAULT_ROBOT).grasp
    assert g is not None and describe("hand_arm").grasp is None
    m = describe(DEFAULT_ROBOT).execution_point_map
    assert [m[p] for p in g.gripper_points] == ["left_tip_a", "left_tip_b"] and m[g.press_point] == "right_tip"


def test_malformed_xml_and_missing_meshes_raise_urdf_errors(tmp_path):
    broken = tmp_path / "broken.urdf"
    broken.write_text('<robot name="r"><link name="a"></robot>')
    with pytest.raises(URDFError, match="mismatched tag"):
        parse_urdf(broken)
    mesh = tmp_path / "mesh.urdf"
    mesh.write_text('<robot name="m"><link name="a"><collision><geometry><mesh filename="nope.stl"/></geometry>'
                    '</collision></link></robot>')
    with pytest.raises(URDFError, match="nope.stl not found"):
        parse_urdf(mesh)
    nan = tmp_path / "nan.urdf"
    nan.write_text('<robot name="n"><link name="a"/><link name="b"/><joint name="j" type="fixed"><parent link="a"/>'
                   '<child link="b"/><origin xyz="0 nan 0"/></joint></robot>')
    with pytest.raises(URDFError, match="not finite"):
        parse_urdf(nan)


def test_derived_points_come_from_the_descriptions():
    plan = PlanArrays(0.0, 0.1, ["right/4", "right/8"], np.zeros((1, 2, 3)), np.ones((1, 2), bool))
    with pytest.raises(ValueError, match="no robot description derives the plan point 'right/grip_axis'"):
        with_derived_point(plan, "right/grip_axis")
    plan = PlanArrays(0.0, 0.1, ["left/4", "left/8"], np.array([[[0, 0, 0.01], [0.0, 0.005, 0.01]]]),
                      np.ones((1, 2), bool))
    out = with_derived_point(plan, "left/grip_axis")
    offset = describe(DEFAULT_ROBOT).derived_points[0].offset
    np.testing.assert_allclose(out.positions[0, -1], [0.0, 0.0025 + offset, 0.01])
