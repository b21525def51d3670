"""Repeatability of the simulated robot as in thesis table 6.1 (pure of Zenoh: drives the world's
MuJoCo model through the board simulator in-process).

Each single-axis test drives the axis 12 times from a start pose by 1 cm (prismatic) or 60 deg
(revolute) to a virtual dial gauge and back; the gauge reads the measured point's displacement
along the gauge axis after the motion settles. The randomized test moves X, Y and Z together
between two random poses (10 cm horizontal, 8 cm vertical range) 10 times and reads the wrist.
Sources of spread in simulation: 15-bit encoder quantization with one LSB of noise, controller
settling, and the different approach directions of the randomized test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from services.robot.board_sim import BoardSim
from services.world.sim import WorldSim
from shared.kinematics import load_robot
from shared.protocols.robot_board import CommandFrame, Mode
from shared.robots.registry import DEFAULT_ROBOT

SETTLE_S = 0.6


@dataclass
class TestCase:
    label: str
    joints: tuple[str, ...]
    point: str  # measured frame
    repeats: int


CASES = [TestCase("Y", ("left_y",), "left_wrist_point", 12),
         TestCase("Z", ("left_z",), "left_tip_a", 12),
         TestCase("Wrist", ("left_wrist",), "left_tip_a", 12),
         TestCase("Gripper", ("left_finger_a",), "left_tip_a", 12),
         TestCase("X, Y, Z", ("left_x", "left_y", "left_z"), "left_wrist_point", 10)]


class Rig:
    def __init__(self, seed: int) -> None:
        self.sim = WorldSim(seed=seed)
        self.sim.set_robot_mode("robot")
        self.board = BoardSim(self.sim.joint_names, seed=seed)
        self.model = load_robot(DEFAULT_ROBOT)
        self.names = self.sim.joint_names
        self.seq = 0

    def home(self) -> np.ndarray:
        """The measuring pose: both arms raised clear of the table, the gripper slightly open."""
        q = np.zeros(len(self.names))
        q[self.names.index("left_z")] = 0.2
        q[self.names.index("right_z")] = 0.1
        q[self.names.index("left_finger_a")] = 0.01
        return q

    def move(self, target: np.ndarray, duration: float) -> None:
        """Linear interpolation to target over ``duration``, then settle; commands at 250 Hz.
        Coupled joints (the gripper's second finger) follow their masters."""
        target = self.model.couple(target)
        q0, _ = self.sim.joint_state()
        n = len(self.names)
        t_start = self.sim.time
        steps = int((duration + SETTLE_S) / self.sim.physics_dt)
        for k in range(steps):
            s = min(1.0, (self.sim.time - t_start) / duration)
            if k % 2 == 0:
                goal = q0 + (target - q0) * (3 * s ** 2 - 2 * s ** 3)
                self.board.receive(CommandFrame(self.seq, np.full(n, Mode.POSITION, np.uint8), goal, np.zeros(n),
                                                np.zeros(n), np.zeros(n), np.zeros(n)), self.sim.time)
                self.seq += 1
            q, qd = self.sim.joint_state()
            effort, _ = self.board.step(self.sim.time, q, qd, self.sim.physics_dt)
            self.sim.set_efforts(effort)
            self.sim.step(1)

    def point(self, frame: str) -> np.ndarray:
        q, _ = self.sim.joint_state()
        return self.model.fk(q)[frame][:3, 3]


def run(seed: int = 0, progress: bool = True) -> list[dict]:

    rng = np.random.default_rng(seed)
    rig = Rig(seed)
    names = rig.names
    home = rig.home()
    rig.move(home, 1.0)
    results = []
    total = sum(c.repeats for c in CASES)
    bar = tqdm(total=total, desc="repeatability", disable=not progress)
    for case in CASES:
        readings = []
        for _ in range(case.repeats):
            if case.label == "X, Y, Z":
                a = home.copy()
                b = home.copy()
                for j, span in (("left_x", 0.10), ("left_y", 0.10), ("left_z", 0.08)):
                    a[names.index(j)] += rng.uniform(-span / 2, span / 2)
                    b[names.index(j)] += rng.uniform(-span / 2, span / 2)
                a[names.index("left_z")] = np.clip(a[names.index("left_z")], 0.05, 0.3)
                rig.move(b, 0.8)
                rig.move(a, 0.8)
                if not readings:
                    gauge_pose = a
                rig.move(gauge_pose, 0.8)  # every trial ends at the same gauge pose from elsewhere
                readings.append(rig.point(case.point))
                continue
            j = names.index(case.joints[0])
            touch = home.copy()
            touch[j] += np.radians(60) if case.label == "Wrist" else 0.01
            rig.move(touch, 0.5)
            readings.append(rig.point(case.point))
            rig.move(home, 0.5)
            bar.update(1)
        if case.label == "X, Y, Z":
            bar.update(case.repeats)
        r = np.array(readings)
        # The gauge reads along the direction of the largest spread (its measuring axis).
        centred = r - r.mean(axis=0)
        axis = np.linalg.svd(centred, full_matrices=False)[2][0] if len(r) > 1 else np.array([1.0, 0, 0])
        d = centred @ axis
        results.append({"joints": case.label, "end_effector": "wrist" if "wrist_point" in case.point else "finger tip",
                        "sigma_mm": float(d.std(ddof=1) * 1e3), "three_sigma_mm": float(3 * d.std(ddof=1) * 1e3),
                        "repeats": case.repeats})
    bar.close()
    return results
