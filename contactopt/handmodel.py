"""Our own URDF models of a five-finger hand (24 joints, 20 DoF) and of the hand on a 6-joint arm
(30 joints, 26 DoF), with the joint structure of the Shadow hand and the joint counts of thesis
Table 2.1, built from primitives with yourdfpy and written to contactopt/models/.

Hand frame: origin at the wrist, fingers along +x, palm facing -z. The first, middle and ring
fingers have abduction (J4), proximal flexion (J3), middle (J2) and distal (J1) joints, J1
coupled to J2 (a URDF mimic joint, as the Shadow hand couples them); the little finger adds a
metacarpal joint (J5); the thumb has five joints; the wrist two. Link lengths follow the Shadow
hand's (45 / 25 / 26 mm fingers). Each fingertip carries a 1 cm collision sphere: the shapes
the contact-based policy pairs with the object. The arm is a gantry (prismatic x, y, z, then yaw,
pitch and roll): the joint count of Table 2.1's UR5, not its kinematics.

Regenerate with `python -m contactopt.handmodel`.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import yourdfpy as ud

MODELS = Path(__file__).parent / "models"
TIP_RADIUS = 0.01
FINGER = (0.045, 0.025, 0.026)   # proximal, middle, distal lengths [m]
THUMB = (0.038, 0.032, 0.0275)
# finger name -> (base position on the palm, has a metacarpal joint J5)
FINGERS = {"ff": ((0.095, 0.033, 0.0), False), "mf": ((0.099, 0.011, 0.0), False),
           "rf": ((0.095, -0.011, 0.0), False), "lf": ((0.086, -0.033, 0.0), True)}
THUMB_BASE = (0.03, 0.034, -0.01)


def tf(xyz: tuple[float, ...] = (0, 0, 0), rpy: tuple[float, ...] = (0, 0, 0)) -> np.ndarray:
    """4x4 transform from translation and roll-pitch-yaw (URDF convention R = Rz Ry Rx)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    m = np.eye(4)
    m[:3, :3] = np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                          [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                          [-sp, cp * sr, cp * cr]])
    m[:3, 3] = xyz
    return m


class Builder:
    def __init__(self, root: str) -> None:
        self.links = [ud.Link(name=root)]
        self.joints: list[ud.Joint] = []

    def link(self, name: str, tip: float | None = None, box: tuple[float, ...] | None = None,
             box_at: tuple[float, ...] = (0, 0, 0)) -> None:
        coll = []
        if tip is not None:
            coll.append(ud.Collision(name=f"{name}_tip", origin=tf((tip, 0, 0)),
                                     geometry=ud.Geometry(sphere=ud.Sphere(radius=TIP_RADIUS))))
        if box is not None:
            coll.append(ud.Collision(name=f"{name}_box", origin=tf(box_at),
                                     geometry=ud.Geometry(box=ud.Box(size=np.array(box)))))
        self.links.append(ud.Link(name=name, collisions=coll))

    def joint(self, name: str, parent: str, child: str, xyz: tuple[float, ...], axis: tuple[float, ...],
              lower: float, upper: float, kind: str = "revolute", mimic: str | None = None,
              rpy: tuple[float, ...] = (0, 0, 0)) -> None:
        self.joints.append(ud.Joint(
            name=name, type=kind, parent=parent, child=child, origin=tf(xyz, rpy), axis=np.array(axis, float),
            limit=ud.Limit(lower=lower, upper=upper, effort=10.0, velocity=2.0),
            mimic=None if mimic is None else ud.Mimic(joint=mimic, multiplier=1.0, offset=0.0)))

    def write(self, name: str, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        ud.URDF(robot=ud.Robot(name=name, links=self.links, joints=self.joints)).write_xml_file(str(path))
        # yourdfpy's writer drops <mimic>; add it to the written XML
        tree = ET.parse(path)
        for el in tree.getroot().iter("joint"):
            j = next(j for j in self.joints if j.name == el.get("name"))
            if j.mimic is not None:
                ET.SubElement(el, "mimic", joint=j.mimic.joint, multiplier="1.0", offset="0.0")
        ET.indent(tree)
        tree.write(path, xml_declaration=True, encoding="utf-8")


def add_hand(b: Builder, parent: str) -> None:
    """The hand's 24 joints below `parent` (the wrist mount)."""
    b.link("wrist")
    b.joint("WRJ2", parent, "wrist", (0, 0, 0), (0, 0, 1), -0.5, 0.2)
    b.link("palm", box=(0.1, 0.085, 0.025), box_at=(0.05, 0, 0))
    b.joint("WRJ1", "wrist", "palm", (0, 0, 0), (0, 1, 0), -0.7, 0.5)
    for f, (base, metacarpal) in FINGERS.items():
        up = "palm"
        if metacarpal:
            b.link(f"{f}metacarpal")
            b.joint(f"{f.upper()}J5", up, f"{f}metacarpal", (0.033, base[1], 0), (1, 0, 0), 0.0, 0.8)
            up, base = f"{f}metacarpal", (base[0] - 0.033, 0.0, 0.0)
        b.link(f"{f}knuckle")
        b.joint(f"{f.upper()}J4", up, f"{f}knuckle", base, (0, 0, 1), -0.35, 0.35)
        names = ("proximal", "middle", "distal")
        for k, (n, length) in enumerate(zip(names, FINGER, strict=True)):
            b.link(f"{f}{n}", tip=length if n == "distal" else None)
            parent_link = f"{f}knuckle" if k == 0 else f"{f}{names[k - 1]}"
            at = (0, 0, 0) if k == 0 else (FINGER[k - 1], 0, 0)
            b.joint(f"{f.upper()}J{3 - k}", parent_link, f"{f}{n}", at, (0, 1, 0), 0.0, 1.57,
                    mimic=f"{f.upper()}J2" if n == "distal" else None)
    # thumb: along +y from its base; J5 turns it about the palm's long axis, down to oppose the fingers
    chain = [("thbase", (0, 1, 0), THUMB_BASE, (0.0, 0.0, 1.57)), ("thproximal", (0, 0, 1), (0, 0, 0), (0, 0, 0)),
             ("thhub", (0, 1, 0), (THUMB[0], 0, 0), (0, 0, 0)), ("thmiddle", (0, 0, 1), (0, 0, 0), (0, 0, 0)),
             ("thdistal", (0, 1, 0), (THUMB[1], 0, 0), (0, 0, 0))]
    up = "palm"
    for k, (n, axis, at, rpy) in enumerate(chain):
        b.link(n, tip=THUMB[2] if n == "thdistal" else None)
        b.joint(f"THJ{5 - k}", up, n, at, axis, -1.0, 1.6, rpy=rpy)
        up = n


def build() -> None:
    hand = Builder("mount")
    add_hand(hand, "mount")
    hand.write("hand", MODELS / "hand.urdf")
    arm = Builder("base")
    prev = "base"
    for name, kind, axis in (("ARMX", "prismatic", (1, 0, 0)), ("ARMY", "prismatic", (0, 1, 0)),
                             ("ARMZ", "prismatic", (0, 0, 1)), ("ARMYAW", "revolute", (0, 0, 1)),
                             ("ARMPITCH", "revolute", (0, 1, 0)), ("ARMROLL", "revolute", (1, 0, 0))):
        link = f"arm_{name.lower()}"
        arm.link(link)
        lim = (-0.3, 0.3) if kind == "prismatic" else (-3.0, 3.0)
        arm.joint(name, prev, link, (0, 0, 0), axis, *lim, kind=kind)
        prev = link
    add_hand(arm, prev)
    arm.write("arm_hand", MODELS / "arm_hand.urdf")


if __name__ == "__main__":
    build()
