"""Generates workcell.urdf: the gantry of thesis chapter 6 (kept as code so dimensions stay in one place).

World frame: table top z=0, x forward, y left. Per arm: a carriage on the shared Y rail (y), an
X slide (x), a vertical Z axis (z, positive = down), a wrist (revolute about z). Left arm: a
two-finger parallel gripper (finger_b mimics finger_a); right arm: one rigid finger.
Run: python shared/robots/make_workcell_urdf.py > shared/robots/workcell.urdf
"""

from __future__ import annotations

RAIL_Z = 0.62  # Y rail height
Z_TRAVEL = 0.368  # finger tips reach 2 mm above the table
LINK = """  <link name="{name}">
    <inertial><origin xyz="0 0 0"/><mass value="{mass}"/>
      <inertia ixx="{i}" iyy="{i}" izz="{i}" ixy="0" ixz="0" iyz="0"/></inertial>
{geoms}  </link>
"""
BOX = """    <{kind}><origin xyz="{xyz}"/><geometry><box size="{size}"/></geometry>{mat}</{kind}>
"""
CYL = """    <{kind}><origin xyz="{xyz}"/><geometry><cylinder radius="{r}" length="{l}"/></geometry>{mat}</{kind}>
"""
JOINT = """  <joint name="{name}" type="{type}">
    <parent link="{parent}"/><child link="{child}"/>
    <origin xyz="{xyz}" rpy="0 0 0"/>{axis}{limit}{mimic}
  </joint>
"""


def link(name: str, mass: float, shapes: list[tuple]) -> str:
    geoms = ""
    for shape in shapes:
        for kind in ("visual", "collision"):
            mat = '<material name="alu"/>' if kind == "visual" else ""
            if shape[0] == "box":
                geoms += BOX.format(kind=kind, xyz=shape[1], size=shape[2], mat=mat)
            else:
                geoms += CYL.format(kind=kind, xyz=shape[1], r=shape[2], l=shape[3], mat=mat)
    return LINK.format(name=name, mass=mass, i=max(1e-5, mass * 1e-3), geoms=geoms)


def joint(name: str, kind: str, parent: str, child: str, xyz: str, axis: str = "",
          lo: float = 0, hi: float = 0, vel: float = 0, effort: float = 0, mimic: str = "") -> str:
    axis_s = f'\n    <axis xyz="{axis}"/>' if axis else ""
    limit = f'\n    <limit lower="{lo}" upper="{hi}" velocity="{vel}" effort="{effort}"/>' if kind != "fixed" else ""
    mimic_s = f'\n    <mimic joint="{mimic}" multiplier="1" offset="0"/>' if mimic else ""
    return JOINT.format(name=name, type=kind, parent=parent, child=child, xyz=xyz, axis=axis_s, limit=limit,
                        mimic=mimic_s)


def point(name: str, parent: str, xyz: str) -> str:
    return (f'  <link name="{name}"/>\n' + joint(f"{name}_fixed", "fixed", parent, name, xyz))


def arm(side: str) -> str:
    s = 1 if side == "left" else -1
    y_lo, y_hi = (-0.05, 0.35) if side == "left" else (-0.35, 0.05)
    out = link(f"{side}_carriage", 1.0, [("box", "0 0 0", "0.12 0.08 0.05")])
    out += joint(f"{side}_y", "prismatic", "base", f"{side}_carriage", f"0 {0.15 * s} {RAIL_Z}", "0 1 0",
                 y_lo - 0.15 * s, y_hi - 0.15 * s, 0.5, 200)
    out += link(f"{side}_slide", 0.8, [("box", "0 0 -0.04", "0.06 0.06 0.03")])
    out += joint(f"{side}_x", "prismatic", f"{side}_carriage", f"{side}_slide", "0 0 0", "1 0 0",
                 -0.3, 0.3, 0.5, 200)
    out += link(f"{side}_column", 0.5, [("box", "0 0 0.1", "0.03 0.03 0.2")])
    out += joint(f"{side}_z", "prismatic", f"{side}_slide", f"{side}_column", "0 0 -0.07", "0 0 -1",
                 0.0, Z_TRAVEL, 0.5, 200)
    out += link(f"{side}_hand", 0.3, [("cyl", "0 0 -0.02", 0.025, 0.04)])
    out += joint(f"{side}_wrist", "revolute", f"{side}_column", f"{side}_hand", "0 0 -0.03", "0 0 1",
                 -3.1416, 3.1416, 6.0, 5)
    out += point(f"{side}_wrist_point", f"{side}_hand", "0 0 0")
    if side == "left":
        for f, sign in (("a", 1), ("b", -1)):
            out += link(f"left_finger_{f}", 0.05, [("box", f"0 {0.003 * sign} -0.07", "0.012 0.004 0.08")])
            out += joint(f"left_finger_{f}", "prismatic", "left_hand", f"left_finger_{f}", "0 0 -0.04",
                         f"0 {sign} 0", 0.0, 0.04, 0.2, 40, mimic="left_finger_a" if f == "b" else "")
            out += point(f"left_tip_{f}", f"left_finger_{f}", "0 0 -0.11")
    else:
        out += link("right_finger", 0.05, [("box", "0.02 0 -0.07", "0.008 0.008 0.08")])
        out += joint("right_finger_mount", "fixed", "right_hand", "right_finger", "0 0 -0.04")
        out += point("right_tip", "right_finger", "0.02 0 -0.11")
    return out


def urdf() -> str:
    body = '<?xml version="1.0"?>\n<robot name="workcell">\n'
    body += '  <material name="alu"><color rgba="0.7 0.72 0.75 1"/></material>\n'
    body += '  <link name="base"/>\n'
    body += link("y_rail", 2.0, [("box", f"0 0 {RAIL_Z + 0.04}", "0.04 0.8 0.03")])
    body += joint("y_rail_mount", "fixed", "base", "y_rail", "0 0 0")
    body += arm("left") + arm("right")
    return body + "</robot>\n"


if __name__ == "__main__":
    print(urdf(), end="")
