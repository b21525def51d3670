"""Generates hand_arm.urdf: a 6-DoF arm (UR-like proportions) with a four-finger hand whose
middle and distal finger joints are coupled (mimic), as in the hand-arm systems of thesis 7.3.1.
Run: python shared/robots/make_hand_arm_urdf.py > shared/robots/hand_arm.urdf
"""

from __future__ import annotations

from shared.robots.make_workcell_urdf import joint, link, point

ARM = [  # name, parent xyz offset, axis, lower, upper, link shape
    ("shoulder_pan", "0 0 0.15", "0 0 1", -3.14, 3.14, ("cyl", "0 0 0.05", 0.06, 0.1)),
    ("shoulder_lift", "0 0.1 0.05", "0 1 0", -3.14, 0.0, ("box", "0.2 0 0", "0.42 0.08 0.08")),
    ("elbow", "0.42 -0.08 0", "0 1 0", -2.8, 2.8, ("box", "0.19 0 0", "0.39 0.06 0.06")),
    ("wrist_1", "0.39 0.07 0", "0 1 0", -3.14, 3.14, ("cyl", "0 0.05 0", 0.04, 0.08)),
    ("wrist_2", "0 0.09 0", "0 0 1", -3.14, 3.14, ("cyl", "0 0 0.04", 0.04, 0.08)),
    ("wrist_3", "0 0 0.09", "0 1 0", -3.14, 3.14, ("box", "0 0.04 0", "0.09 0.03 0.09")),
]
FINGERS = {"thumb": (0.03, -0.035), "index": (0.09, -0.02), "middle": (0.095, 0.0), "ring": (0.09, 0.02)}


def urdf() -> str:
    out = '<?xml version="1.0"?>\n<robot name="hand_arm">\n'
    out += '  <material name="alu"><color rgba="0.7 0.72 0.75 1"/></material>\n  <link name="base"/>\n'
    parent = "base"
    for name, xyz, axis, lo, hi, shape in ARM:
        out += link(f"{name}_link", 2.0, [shape])
        out += joint(name, "revolute", parent, f"{name}_link", xyz, axis, lo, hi, 3.0, 50)
        parent = f"{name}_link"
    out += link("palm", 0.4, [("box", "0 0.06 0", "0.1 0.1 0.03")])
    out += joint("palm_mount", "fixed", parent, "palm", "0 0.06 0")
    out += point("wrist_point", "palm", "0 0 0")
    for name, (x, z) in FINGERS.items():
        # fingers extend along the palm's +y; proximal joint flexes about x, middle+distal coupled
        base = f"0 {x + 0.02} {z}"
        out += link(f"{name}_proximal", 0.03, [("box", "0 0.022 0", "0.016 0.045 0.016")])
        out += joint(f"{name}_j1", "revolute", "palm", f"{name}_proximal", base, "1 0 0", 0.0, 1.6, 4.0, 2)
        out += link(f"{name}_middle", 0.02, [("box", "0 0.013 0", "0.014 0.026 0.014")])
        out += joint(f"{name}_j2", "revolute", f"{name}_proximal", f"{name}_middle", "0 0.045 0", "1 0 0", 0.0, 1.6,
                     4.0, 1)
        out += link(f"{name}_distal", 0.01, [("box", "0 0.011 0", "0.012 0.022 0.012")])
        out += joint(f"{name}_j3", "revolute", f"{name}_middle", f"{name}_distal", "0 0.026 0", "1 0 0", 0.0, 1.6,
                     4.0, 1, mimic=f"{name}_j2")
        out += point(f"{name}_tip", f"{name}_distal", "0 0.022 0")
    return out + "</robot>\n"


if __name__ == "__main__":
    print(urdf(), end="")
