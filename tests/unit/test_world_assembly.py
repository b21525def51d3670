"""The assembly task's physics in robot mode (the connector's snap-fit), the teacher's square pinch,
and the gripper's derived yaw point."""

from __future__ import annotations

import numpy as np
import pytest

from services.trajopt.mapping import PlanArrays, goals_for_horizon, with_grip_axis
from services.world.sim import SEAT_FORCE_N, WorldSim
from services.world.teacher import OBJECT_POINTS, Teacher, rot_z
from shared.robots.make_workcell_urdf import GRIP_AXIS

CAMERA = OBJECT_POINTS["assembly"]["camera"]
BOARD = OBJECT_POINTS["assembly"]["board"]


def place_module_on_connector(sim: WorldSim, offset=(0.0, 0.0)) -> None:
    """Puts the module where the teacher seats it (connector on the board's), shifted by offset."""
    pose = sim.body_poses()["board"]
    yaw = 2 * np.arctan2(pose[6], pose[3])
    conn = pose[:3] + rot_z(yaw) @ np.array(BOARD["connector"])
    cam_yaw = yaw + np.pi
    origin = conn - rot_z(cam_yaw) @ np.array(CAMERA["connector"]) + [offset[0], offset[1], 0.001]  # drops on
    adr = sim._free["camera"]
    sim.data.qpos[adr:adr + 3] = origin
    sim.data.qpos[adr + 3:adr + 7] = [np.cos(cam_yaw / 2), 0, 0, np.sin(cam_yaw / 2)]
    sim.data.qvel[sim._free_dof["camera"]:sim._free_dof["camera"] + 6] = 0.0


def push_and_lift(sim: WorldSim, push_n: float) -> None:
    cam = sim.model.body("camera").id
    sim.data.xfrc_applied[cam, 2] = -push_n  # pressed onto the board ...
    sim.step(100)
    sim.data.xfrc_applied[cam, 2] = 0.3  # ... then lifted (module + board weigh ~0.1 N)
    sim.step(300)
    sim.data.xfrc_applied[cam, 2] = 0.0


@pytest.fixture
def sim():
    s = WorldSim("assembly", seed=0, width=32, height=24)
    s.start_demo(4)
    s.set_robot_mode("robot")
    s.step(50)  # the objects settle on the table
    return s


def test_an_aligned_connector_pressed_home_snaps_and_the_board_comes_up_with_the_module(sim):
    place_module_on_connector(sim)
    sim.step(20)
    assert sim.connector_gap() < 0.003 and sim.seated_at is None  # resting on it is not seated
    push_and_lift(sim, 2 * SEAT_FORCE_N)
    assert sim.seated_at is not None
    assert sim.assembly_success()  # connector still home, board 2 cm up
    sim.start_demo(5)  # a new demonstration releases the latch
    assert sim.seated_at is None and not sim.data.eq_active[sim._latch]


@pytest.mark.parametrize("offset, push", [((0.005, 0.0), 2.0), ((0.0, 0.0), 0.5)])
def test_a_misaligned_or_unpressed_connector_does_not_snap(sim, offset, push):
    place_module_on_connector(sim, offset)
    sim.step(20)
    push_and_lift(sim, push * SEAT_FORCE_N)
    assert sim.seated_at is None and not sim.assembly_success()
    board_z = min(sim.object_keypoints()[1][sim.object_keypoints()[0].index(f"board/c{i}")][2] for i in range(4))
    assert board_z < 0.005  # the board stayed on the table


def test_the_teachers_pinch_is_square_to_the_lens_body_for_either_hand():
    for seed, hand in ((4, "left"), (5, "right")):
        t = Teacher("assembly", seed, grasp_hand=hand)
        g = ("left", "right").index(hand)
        for time in (t.grasp_window[0] + 0.01, t.insert_time - 0.01):
            hands = t._hands(time)
            line = hands[g, 8] - hands[g, 4]
            yaw = t._objects(time, hands)["camera"][1]
            axis = np.array([np.cos(yaw), np.sin(yaw)])
            assert abs(line[:2] @ axis) / np.linalg.norm(line[:2]) < 1e-6  # fingertips on opposite faces


def test_the_grip_axis_point_gives_the_gripper_yaw_a_lever():
    names = ["left/4", "left/8", "right/8"]
    pos = np.array([[[0.0, 0.0, 0.01], [0.0, 0.005, 0.01], [0.1, 0.0, 0.02]]] * 3)
    mask = np.ones((3, 3), bool)
    mask[2, 0] = False
    plan = with_grip_axis(PlanArrays(0.0, 0.1, names, pos, mask))
    assert plan.names[-1] == "left/grip_axis"
    np.testing.assert_allclose(plan.positions[0, -1], [0.0, 0.0025 + GRIP_AXIS, 0.01])
    assert plan.mask[:, -1].tolist() == [True, True, False]  # needs both fingertips
    goals, gmask = goals_for_horizon(PlanArrays(0.0, 0.1, names, pos, mask), ["left/grip_axis"], 0.0, 0.1, 2)
    np.testing.assert_allclose(goals[0, 0], plan.positions[0, -1])
    assert gmask[0, 0]
    assert with_grip_axis(PlanArrays(0.0, 0.1, ["right/8"], pos[:, 2:], mask[:, 2:])).names == ["right/8"]
