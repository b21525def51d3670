"""Generates hand_arm.urdf: the hand-arm systems of thesis 7.3.1, a 6-DoF arm with UR10-like link
lengths and a humanoid hand (thumb + index, middle, ring) whose middle and distal finger joints are
mechanically coupled (``<finger>_j3`` mimics ``<finger>_j2``, as in the Shadow hands).

The root link ``base`` is the workcell frame (table centre, z up, as in workcell.urdf); the arm
stands at MOUNT_XYZ beside the table's right edge. Arm zero pose: straight up. The palm's +z
continues the last link, its -y is the palm side; fingers extend along their local +z and flex
about their local +x towards the palm. Links are capsule-like (thesis 7.4): cylinders along the
bones, spheres at the tips.

Run: .venv/bin/python -m shared.robots.make_hand_arm_urdf  (writes hand_arm.urdf)
"""

from __future__ import annotations

from math import pi
from pathlib import Path

from shared.robots.urdf_writer import HEADER, MATERIALS, joint, link, point

HERE = Path(__file__).parent
# Where the arm stands in the workcell (the root link "base" is the cell frame: table centre, z up):
# on the table's right edge (-y), its pan frame turned so that shoulder_lift > 0 leans over the table.
MOUNT_XYZ, MOUNT_YAW = (0.0, -0.5, 0.0), pi / 2
# name, parent link, origin xyz, axis, limit (rad), velocity (rad/s), effort (Nm), link shape
ARM = [
    ("shoulder_pan", "base", f"{MOUNT_XYZ[0]:g} {MOUNT_XYZ[1]:g} {MOUNT_XYZ[2] + 0.128:g}", "0 0 1", pi, 2.0, 330,
     ("cylinder", "0 0 0", (0.075, 0.17))),
    ("shoulder_lift", "shoulder_pan_link", "0 0.176 0", "0 1 0", pi, 2.0, 330,
     ("cylinder", "0 0 0.306", (0.06, 0.612))),
    ("elbow", "shoulder_lift_link", "0 -0.137 0.612", "0 1 0", 2.9, 3.0, 150,
     ("cylinder", "0 0 0.286", (0.045, 0.572))),
    ("wrist_1", "elbow_link", "0 0 0.572", "0 1 0", pi, 3.0, 56, ("cylinder", "0 0.06 0", (0.045, 0.11))),
    ("wrist_2", "wrist_1_link", "0 0.116 0", "0 0 1", pi, 3.0, 56, ("cylinder", "0 0 0.06", (0.045, 0.11))),
    ("wrist_3", "wrist_2_link", "0 0 0.116", "0 1 0", pi, 3.0, 28, ("cylinder", "0 0.04 0", (0.04, 0.07))),
]
# finger -> (base xyz in the palm, base rpy, bone lengths proximal/middle/distal)
FINGERS = {
    "thumb": ("0.035 -0.018 0.03", f"0 {pi / 4:.5f} 0", (0.038, 0.032, 0.027)),
    "index": ("0.03 0 0.1", "0 0 0", (0.045, 0.025, 0.022)),
    "middle": ("0.0 0 0.104", "0 0 0", (0.045, 0.025, 0.022)),
    "ring": ("-0.03 0 0.1", "0 0 0", (0.045, 0.025, 0.022)),
}
FINGER_LIMITS = {"j1": (-0.26, 1.57), "j2": (0.0, 1.57), "j3": (0.0, 1.57)}
FINGER_MOTION = dict(velocity=2.0, effort=2.0)
RADIUS = {"proximal": 0.010, "middle": 0.009, "distal": 0.008}


def finger(name: str, xyz: str, rpy: str, bones: tuple[float, float, float]) -> str:
    out = ""
    if name == "thumb":  # opposition: rotates the whole thumb about its own long axis
        out += joint("thumb_j0", "revolute", "palm", "thumb_base", xyz, "0 0 1", -1.0, 1.0, rpy=rpy, **FINGER_MOTION)
        out += link("thumb_base", 0.01, [("sphere", "0 0 0", (0.012,))], "dark")
        parent, xyz, rpy = "thumb_base", "0 0 0", "0 0 0"
    else:
        parent = "palm"
    offsets = [xyz, f"0 0 {bones[0]}", f"0 0 {bones[1]}"]
    for k, (bone, length) in enumerate(zip(("proximal", "middle", "distal"), bones, strict=True), start=1):
        lo, hi = FINGER_LIMITS[f"j{k}"]
        child = f"{name}_{bone}"
        out += joint(f"{name}_j{k}", "revolute", parent, child, offsets[k - 1], "1 0 0", lo, hi,
                     mimic=f"{name}_j2" if k == 3 else "", rpy=rpy if k == 1 else "0 0 0", **FINGER_MOTION)
        r = RADIUS[bone]
        shapes = [("cylinder", f"0 0 {length / 2}", (r, length))]
        if bone == "distal":
            shapes.append(("sphere", f"0 0 {length}", (r,)))
        out += link(child, 0.02, shapes)
        parent = child
    out += point(f"{name}_tip", f"{name}_distal", f"0 0 {bones[2] + RADIUS['distal']}")
    return out


def urdf() -> str:
    out = HEADER.format(name="hand_arm") + MATERIALS
    out += '  <mujoco><compiler fusestatic="false" discardvisual="true"/></mujoco>\n'
    out += '  <link name="base"/>\n'
    for name, parent, xyz, axis, lim, vel, eff, shape in ARM:
        out += joint(name, "revolute", parent, f"{name}_link", xyz, axis, -lim, lim, vel, eff,
                     rpy=f"0 0 {MOUNT_YAW:.5f}" if parent == "base" else "0 0 0")
        out += link(f"{name}_link", 3.0 if name.startswith(("shoulder", "elbow")) else 1.2, [shape], "alu",
                    rpy="0 0 0" if shape[1].startswith("0 0") or name == "wrist_2" else f"{pi / 2:.5f} 0 0")
    # palm +z continues wrist_3's +y axis
    out += joint("hand_mount", "fixed", "wrist_3_link", "palm", "0 0.082 0", rpy=f"{-pi / 2:.5f} 0 0")
    out += link("palm", 0.4, [("box", "0 0 0.05", (0.095, 0.03, 0.1))], "dark")
    out += point("wrist_point", "palm", "0 0 0")
    for name, (xyz, rpy, bones) in FINGERS.items():
        out += finger(name, xyz, rpy, bones)
    return out + "</robot>\n"


def main() -> None:
    (HERE / "hand_arm.urdf").write_text(urdf())


if __name__ == "__main__":
    main()
