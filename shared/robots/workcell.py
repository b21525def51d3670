"""The workcell gantry (thesis chapter 6; geometry in make_workcell_urdf.py): two arms on one rail,
a parallel gripper on the left arm and a single pressing finger on the right."""

from __future__ import annotations

from pathlib import Path

from shared.robots.description import DerivedPoint, GraspRoles, RobotDescription

# URDF document order of the moving joints (make_workcell_urdf.py writes them so)
JOINTS = ("left_x", "left_y", "left_z", "left_wrist", "left_finger_a", "left_finger_b",
          "right_x", "right_y", "right_z", "right_wrist")
GRIP_AXIS = 0.03  # m, pads' midpoint -> left_grip_axis, in the URDF and in the derived plan point alike
# The gripper executes the left hand's thumb and index tips, the finger the right index tip (thesis 7.6).
POINT_MAP = {"left/4": "left_tip_a", "left/8": "left_tip_b", "right/8": "right_tip"}
# A derived point pins the gripper's yaw: its two pads are only 4-5 mm apart.
GRIP_POINT = DerivedPoint("left/grip_axis", "left/4", "left/8", GRIP_AXIS)
# Cross-arm link pairs that can meet: carriages share the Y rail, slides hang at one height,
# columns, hands and fingers meet when both arms work near the middle.
COLLISION_PAIRS = (
    ("left_carriage", "right_carriage"), ("left_slide", "right_slide"), ("left_column", "right_column"),
    ("left_column", "right_hand"), ("left_hand", "right_column"), ("left_hand", "right_hand"),
    ("left_finger_a", "right_finger"), ("left_finger_b", "right_finger"), ("left_hand", "right_finger"),
    ("left_finger_a", "right_hand"), ("left_finger_b", "right_hand"),
)
# MuJoCo: damping of belts and carriages on the linear axes, light wrists and fingers
SIM_DYNAMICS = {j: (2.0 if j.endswith(("_x", "_y", "_z")) else 0.05, 0.01) for j in JOINTS}

DESCRIPTION = RobotDescription(
    name="workcell",
    urdf=Path(__file__).parent / "workcell.urdf",
    joints=JOINTS,
    board_channels={j: i for i, j in enumerate(JOINTS)},
    point_map=POINT_MAP,
    execution_point_map={**POINT_MAP, GRIP_POINT.name: "left_grip_axis"},
    derived_points=(GRIP_POINT,),
    collision_pairs=COLLISION_PAIRS,
    sim_dynamics=SIM_DYNAMICS,
    # left_finger_b follows left_finger_a by a MuJoCo equality (URDF mimic): no motor of its own
    sim_motors=("left_y", "left_x", "left_z", "left_wrist", "left_finger_a", "right_y", "right_x", "right_z",
                "right_wrist"),
    grasp=GraspRoles(gripper_points=("left/4", "left/8"), press_point="right/8",
                     gripper_joints=("left_finger_a", "left_finger_b"), gripper_lift="left_z",
                     gripper_wrist="left_wrist", press_joint="right_z"),
)
