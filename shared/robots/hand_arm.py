"""The hand-arm system (thesis 7.3.1; geometry in make_hand_arm_urdf.py): a 6-DoF arm with
harmonic drives and a four-finger hand driven by pneumatic muscle pairs, executing the right hand."""

from __future__ import annotations

from pathlib import Path

from shared.robots.description import RobotDescription

# URDF document order of the moving joints (make_hand_arm_urdf.py writes them so): the arm, then per
# finger (thumb first) its joints j0 (thumb opposition only), j1, j2, j3
ARM_JOINTS = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")
FINGER_JOINTS = tuple(f"{f}_j{k}" for f in ("thumb", "index", "middle", "ring") for k in range(4) if k or f == "thumb")
JOINTS = ARM_JOINTS + FINGER_JOINTS
POINT_MAP = {"right/0": "wrist_point", "right/4": "thumb_tip", "right/8": "index_tip", "right/12": "middle_tip",
             "right/16": "ring_tip"}
# Human keypoint chains (base, joint, next) per finger joint: <finger>_j1 MCP, _j2 PIP, _j3 DIP; the
# thumb takes the human thumb's CMC, MCP and IP (its j3 repeats the IP: it mimics j2 in the URDF).
CHAINS = {
    "thumb": [(1, 2, 3), (2, 3, 4), (2, 3, 4)],
    "index": [(0, 5, 6), (5, 6, 7), (6, 7, 8)],
    "middle": [(0, 9, 10), (9, 10, 11), (10, 11, 12)],
    "ring": [(0, 13, 14), (13, 14, 15), (14, 15, 16)],
}
# MuJoCo joint dynamics: (damping N m s/rad, armature kg m^2). Armature is the motor's reflected
# inertia (rotor inertia x gear ratio^2: about 1 kg m^2 behind a UR10's 101:1 shoulder drives), which
# also keeps the board's PD loops stable at the 2 ms physics step.
DYNAMICS = {"shoulder": (1.0, 1.0), "elbow": (1.0, 1.0), "wrist": (0.5, 0.2), "finger": (0.01, 0.001)}


def _group(joint: str) -> str:
    return next((g for g in ("shoulder", "elbow", "wrist") if joint.startswith(g)), "finger")


DESCRIPTION = RobotDescription(
    name="hand_arm",
    urdf=Path(__file__).parent / "hand_arm.urdf",
    joints=JOINTS,
    board_channels={j: i for i, j in enumerate(JOINTS)},
    point_map=POINT_MAP,
    execution_point_map=POINT_MAP,
    finger_flexion={f"{f}_j{k}": chain for f, chains in CHAINS.items() for k, chain in enumerate(chains, start=1)},
    finger_hand="right",
    # over the table's right half with the fingers straight (the arm's zero pose points straight up)
    home={"shoulder_pan": 0.33, "shoulder_lift": -0.71, "elbow": 2.6, "wrist_1": 0.34, "wrist_2": -2.13,
          "wrist_3": -0.4},
    pneumatic_joints=FINGER_JOINTS,
    harmonic_joints=ARM_JOINTS,
    sim_dynamics={j: DYNAMICS[_group(j)] for j in JOINTS},
    # a motor per independent joint; each <finger>_j3 follows its j2 by a MuJoCo equality (URDF mimic)
    sim_motors=tuple(j for j in JOINTS if not j.endswith("_j3")),
)
