"""Generates workcell.urdf and its convex mesh: the two-arm gantry of thesis chapter 6.

World frame: table top at z=0, x forward (away from the robot's home side), y to the left; the
aluminium frame is 0.8 m x 0.8 m centred at the origin and 0.7 m high. Per arm: a carriage on
the shared Y rail under the top of the frame (``<arm>_y``),
an X slide (``<arm>_x``, value = world x), a vertical Z axis that lowers the column
(``<arm>_z``, axis -z, value = how far down), and a wrist rotating about z. The carriage joint
(``<arm>_y``) counts from the arm's home on the rail (y = +0.15 left, -0.15 right), so the
all-zero joint vector is a safe home pose with the carriages 30 cm apart; the carriages cover
world y in [-0.12, 0.35] (left) and [-0.35, 0.12] (right) and can touch: a collision pair. The left arm carries a
two-finger parallel gripper (``left_finger_b`` mimics ``left_finger_a``; each finger opens 0..4 cm
in opposite directions), the right arm a single rigid finger 2 cm off the wrist axis.
Gripper finger ends are at z = 0.26 - q_z, so the Z travel of 0.259 m reaches 1 mm above the table:
the camera module's lens body is 4 mm tall. The gripper's keypoints (``left_tip_a/b``) are the finger
pads' centres, 3 mm above the finger ends and 1 mm inside the inner faces: that is where the
teacher's thumb and index tips go when they pinch.

Run: .venv/bin/python -m shared.robots.make_workcell_urdf  (writes workcell.urdf + meshes/)
"""

from __future__ import annotations

from pathlib import Path

from shared.robots.urdf_writer import HEADER, MATERIALS, frustum, joint, link, point, write_stl
from shared.robots.workcell import GRIP_AXIS

HERE = Path(__file__).parent
FRAME_SIZE = 0.8
FRAME_HEIGHT = 0.7
RAIL_Z = 0.66  # carriage centre on the shared Y rail
X_DROP = 0.04  # carriage centre -> X slide centre
Z_DROP = 0.03  # X slide centre -> top of the Z column
COLUMN = 0.25  # column length: Z column top -> wrist joint
TIP = 0.08  # wrist joint -> fingertips
Z_TRAVEL = 0.259  # finger ends down to 1 mm above the table
PAD_HEIGHT = 0.003  # finger end -> pad centre (the gripper keypoints)
Y_HOME = {"left": 0.15, "right": -0.15}
Y_RANGE = {"left": (-0.12, 0.35), "right": (-0.35, 0.12)}  # world y of the carriage (shared rail)
X_RANGE = (-0.3, 0.3)
LINEAR = dict(velocity=0.5, effort=200.0)  # belt-driven 57BL axes
WRIST = dict(velocity=6.0, effort=5.0)  # 42BLF with 5:1 reduction
WRIST_TRAVEL = 6.28319  # +-1 turn (a cable wrap): a pinch that turns ~200 deg stays inside it
FINGER = dict(velocity=0.2, effort=40.0)
GRIPPER_MESH = "meshes/gripper_head.stl"
HEAD_HEIGHT = 0.035


def write_meshes() -> None:
    """The gripper head: a convex frustum, wide at the wrist flange and narrow at the finger rails."""
    v, t = frustum(bottom=(0.05, 0.09), top=(0.06, 0.06), height=HEAD_HEIGHT)
    write_stl(HERE / GRIPPER_MESH, v, t)


def arm(side: str) -> str:
    """One arm in the description's joint order (workcell.JOINTS: x before y in the document; the chain
    is base -> y -> x -> z -> wrist)."""
    lo_y, hi_y = (v - Y_HOME[side] for v in Y_RANGE[side])
    out = joint(f"{side}_x", "prismatic", f"{side}_carriage", f"{side}_slide", f"0 0 {-X_DROP}", "1 0 0",
                *X_RANGE, **LINEAR)
    out += joint(f"{side}_y", "prismatic", "base", f"{side}_carriage", f"0 {Y_HOME[side]} {RAIL_Z}", "0 1 0",
                 round(lo_y, 6), round(hi_y, 6), **LINEAR)
    out += joint(f"{side}_z", "prismatic", f"{side}_slide", f"{side}_column", f"0 0 {-Z_DROP}", "0 0 -1",
                 0.0, Z_TRAVEL, **LINEAR)
    out += joint(f"{side}_wrist", "revolute", f"{side}_column", f"{side}_hand", f"0 0 {-COLUMN}", "0 0 1",
                 -WRIST_TRAVEL, WRIST_TRAVEL, **WRIST)
    out += link(f"{side}_carriage", 1.2, [("box", "0 0 0", (0.10, 0.08, 0.04))], "dark")
    out += link(f"{side}_slide", 0.8, [("box", "0 0 0", (0.07, 0.06, 0.03))], "dark")
    out += link(f"{side}_column", 0.6, [("box", f"0 0 {-COLUMN / 2}", (0.03, 0.03, COLUMN - 0.01))])
    out += point(f"{side}_wrist_point", f"{side}_hand", "0 0 0")
    if side == "left":
        out += link("left_hand", 0.35, [("mesh", "0 0 0", (GRIPPER_MESH, (0.03, 0.045, HEAD_HEIGHT / 2)))])
        # 3 cm from the pads' midpoint along the closing axis (finger_b's side): fixes the gripper's
        # yaw, which the 4-5 mm between the two pad points determines poorly
        out += point("left_grip_axis", "left_hand", f"0 {-GRIP_AXIS} {-TIP + PAD_HEIGHT}")
        for f, s in (("a", 1), ("b", -1)):
            out += joint(f"left_finger_{f}", "prismatic", "left_hand", f"left_finger_{f}", f"0 0 {-HEAD_HEIGHT}",
                         f"0 {s} 0", 0.0, 0.04, mimic="left_finger_a" if f == "b" else "", **FINGER)
            length = TIP - HEAD_HEIGHT
            out += link(f"left_finger_{f}", 0.04, [("box", f"0 {0.004 * s} {-length / 2}", (0.012, 0.006, length))],
                        "steel")
            out += point(f"left_tip_{f}", f"left_finger_{f}", f"0 {0.002 * s} {-length + PAD_HEIGHT}")
    else:
        out += link("right_hand", 0.3, [("cylinder", f"0 0 {-HEAD_HEIGHT / 2}", (0.025, HEAD_HEIGHT))])
        out += joint("right_finger_mount", "fixed", "right_hand", "right_finger", f"0.02 0 {-HEAD_HEIGHT}")
        length = TIP - HEAD_HEIGHT
        out += link("right_finger", 0.03, [("box", f"0 0 {-length / 2 + 0.003}", (0.008, 0.008, length - 0.006)),
                                           ("sphere", f"0 0 {-length + 0.006}", (0.006,))], "steel")
        out += point("right_tip", "right_finger", f"0 0 {-length}")
    return out


def urdf() -> str:
    out = HEADER.format(name="workcell") + MATERIALS
    # MuJoCo: keep keypoint frames as bodies and resolve the mesh path relative to this file.
    out += '  <mujoco><compiler strippath="false" fusestatic="false" discardvisual="true"/></mujoco>\n'
    out += '  <link name="base"/>\n'
    out += joint("y_rail_mount", "fixed", "base", "y_rail", f"0 0 {RAIL_Z + 0.03}")
    out += link("y_rail", 3.0, [("box", "0 0 0", (0.04, FRAME_SIZE, 0.02))], "dark")
    out += arm("left") + arm("right")
    return out + "</robot>\n"


def main() -> None:
    write_meshes()
    (HERE / "workcell.urdf").write_text(urdf())


if __name__ == "__main__":
    main()
