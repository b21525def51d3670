"""What the software knows about one robot model besides its URDF, in one typed record (pure data).

World, trajopt, robot, panel and the robot-in-the-loop evaluation read a robot's description
through ``shared.robots.describe(name)``; the geometry, joints and limits stay in the URDF.

Plan points are named ``<hand>/<keypoint>``: ``hand`` is "left" or "right", ``keypoint`` the index
in the 21-keypoint hand (0 wrist, 4 thumb tip, 8 index tip, 12 middle tip, 16 ring tip) or the
name of a derived point.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class DerivedPoint:
    """A plan point computed from two others (services/trajopt/mapping.py): the midpoint of ``a``
    and ``b`` moved ``offset`` m along a -> b projected on the table plane."""

    name: str
    a: str
    b: str
    offset: float


@dataclass(frozen=True)
class GraspRoles:
    """Which arm grasps and which pushes (services/policy/execute.py): the hand the policy grasps
    with drives ``gripper_points``, the other hand's index tip drives ``press_point``."""

    gripper_points: tuple[str, str]  # plan points the gripper's two pads execute (thumb tip, index tip)
    press_point: str  # plan point the pressing finger executes
    gripper_joints: tuple[str, ...]  # the gripper's finger joints (positive opens)
    gripper_lift: str  # the gripper arm's vertical axis
    gripper_wrist: str  # the gripper arm's wrist
    press_joint: str  # the pressing arm's vertical axis (positive effort pushes down)


@dataclass(frozen=True)
class RobotDescription:
    name: str
    urdf: Path
    # JointState and trajectory order: the URDF's moving joints in document order (a test checks it)
    joints: tuple[str, ...]
    # joint -> control-board channel (services/robot, the world's simulated board). The robot service
    # sends JointState order on the wire, so a description's channels run 0..n-1 in joint order.
    board_channels: dict[str, int]
    # plan point -> robot frame: what the trajectory optimizer makes each frame follow
    point_map: dict[str, str]
    # the map the robot-in-the-loop evaluation executes (may include derived points)
    execution_point_map: dict[str, str]
    derived_points: tuple[DerivedPoint, ...] = ()
    # link pairs the optimizer keeps apart with separating planes (thesis 7.21)
    collision_pairs: tuple[tuple[str, str], ...] = ()
    # robot joint -> human keypoints (a, b, c) whose flexion angle (bone a->b against b->c) it
    # takes, for the hand-pose prior (thesis 7.22); empty for robots without fingers
    finger_flexion: dict[str, tuple[int, int, int]] = field(default_factory=dict)
    finger_hand: str = "right"  # the human hand the finger prior is taken from
    home: dict[str, float] = field(default_factory=dict)  # start pose (rad or m) where zero is not sensible
    pneumatic_joints: tuple[str, ...] = ()  # joints driven by a muscle pair (board PNEUMATIC mode)
    harmonic_joints: tuple[str, ...] = ()  # joints behind 101:1 harmonic drives (board encoder and gains)
    # MuJoCo joint dynamics per moving joint: (damping, armature); motors (in actuator order) on the
    # listed joints, each limited to its URDF effort
    sim_dynamics: dict[str, tuple[float, float]] = field(default_factory=dict)
    sim_motors: tuple[str, ...] = ()
    grasp: GraspRoles | None = None

    @property
    def board_order(self) -> list[str]:
        """Joints in board-channel order."""
        return sorted(self.board_channels, key=self.board_channels.__getitem__)

    def problems(self, joint_names: list[str], frames: list[str], links: list[str]) -> list[str]:
        """What in this description disagrees with its loaded URDF (joint names, frames, links)."""
        out = []
        if list(self.joints) != list(joint_names):
            out.append(f"joints {list(self.joints)} differ from the URDF's moving joints {list(joint_names)}")
        if self.board_order != list(self.joints) or sorted(self.board_channels.values()) != list(
                range(len(self.joints))):
            out.append("board channels must run 0..n-1 in joint order (the robot service sends JointState order)")
        derived = {p.name for p in self.derived_points}
        for what, m in (("point_map", self.point_map), ("execution_point_map", self.execution_point_map)):
            out += [f"{what}: {p} -> {f}: no such frame" for p, f in m.items() if f not in frames]
            out += [f"{what}: {p} is neither a hand keypoint nor a derived point" for p in m
                    if p not in derived and not p.split("/")[-1].isdigit()]
        out += [f"collision pair {a}-{b}: no such link" for a, b in self.collision_pairs
                if a not in links or b not in links]
        named = {**self.finger_flexion, **self.home, **self.sim_dynamics}
        named.update(dict.fromkeys(self.pneumatic_joints + self.harmonic_joints + self.sim_motors))
        if self.grasp is not None:
            g = self.grasp
            named.update(dict.fromkeys(g.gripper_joints + (g.gripper_lift, g.gripper_wrist, g.press_joint)))
            out += [f"grasp point {p} is not in execution_point_map" for p in g.gripper_points + (g.press_point,)
                    if p not in self.execution_point_map]
        out += [f"{j}: not a moving joint" for j in named if j not in joint_names]
        if self.sim_dynamics and set(self.sim_dynamics) != set(joint_names):
            out.append("sim_dynamics must cover every moving joint")
        return out
