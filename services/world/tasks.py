"""The task registry: every demonstrated task of thesis chapter 7 the simulated workcell knows, with
its demonstration protocol, its success test and how the robot executes it.

A task's success test runs on a trajectory (object keypoints, and the force the task's contact
made: the glove's reading for a demonstration, a policy's predicted touch or what its positions
imply for a rollout); `xm eval --task NAME` runs the Table 7.1 protocol on its demonstrations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.world import bottle, latch, wiping
from services.world.teacher import KPA_PER_N, Teacher, assembly_protocol, generate_demo
from shared.demo import HAND_NAMES, TACTILE_REGIONS, Demo

INDEX = TACTILE_REGIONS.index("index")


class UnknownTaskError(ValueError):
    """A task name the registry does not know; the message lists the known ones."""


@dataclass(frozen=True)
class RobotMapping:
    """How the workcell executes a demonstrated task: the grasping hand drives the gripper, the
    other hand's index tip the pressing finger (or it parks), and ``force`` says which predicted
    touch becomes effort along which axis (thesis 7.2.10)."""

    finger: str  # "press": the other hand's index tip drives the finger; "park": it stays home
    force: str  # predicted touch -> effort


@dataclass(frozen=True)
class TaskSpec:
    name: str
    summary: str
    success: str  # what the world's success test checks, in words
    train: int  # demonstrations in the training set (the thesis's count)
    validation: int
    robot: RobotMapping
    measure: str | None = None  # the force-decided outcome `xm eval` reports beside the distances
    executable: bool = False  # `xm eval --execute` runs it on the simulated robot (evaluation/robot_eval.py)

    def protocol(self, seed: int) -> list[Demo]:
        """The task's demonstrations for ``seed``: train first, then validation (meta['split'])."""
        if self.name == "assembly":
            return assembly_protocol(seed)
        demos = []
        for i in range(self.train + self.validation):
            grasp = HAND_NAMES[i % 2]
            press = HAND_NAMES[1 - i % 2]
            glove = press if self.name == "latch" and i != 1 else grasp  # latch: the press is what counts
            d = generate_demo(self.name, seed * 1000 + i, tactile_hand=glove, grasp_hand=grasp, index=i)
            d.meta["split"] = "train" if i < self.train else "validation"
            demos.append(d)
        return demos


GRIP = "thumb + index pressure of the grasping hand shuts the gripper"
TASKS: dict[str, TaskSpec] = {
    "assembly": TaskSpec(
        "assembly", "camera module grasped, its connector placed on the board's and pressed, the board lifted by it",
        "module's connector within 3 mm of the board's and the board lifted 2 cm off the table", 3, 12,
        RobotMapping("press", GRIP + "; the pressing index pressure pushes the finger down"), executable=True),
    "latch": TaskSpec(
        "latch", "the assembly with the connector pressed until it latches (snap at 5 N)",
        "connectors aligned while a finger over them presses >= 5 N (never > 12 N), then the board lifted", 3, 12,
        RobotMapping("press", GRIP + "; the pressing index pressure is the finger's force (force-controlled press)"),
        measure="latched", executable=True),
    "wiping": TaskSpec(
        "wiping", "a sponge grasped, pressed onto a plate's marked area and wiped across it in circles",
        ">= 90 % of the marked area under the pad while it presses with 4-9 N", 5, 10,
        RobotMapping("park", GRIP + "; middle + ring + palm pressure is the gripper's downward force (force control "
                     "in z once the pad is within 5 mm of the plate)"), measure="coverage", executable=True),
    "bottle": TaskSpec(
        "bottle", "a bottle's cap twisted off in repeated turns under the thread's load and lifted",
        "the cap turned a full turn at steps where the grip held it (>= 3 N per finger), then 3 cm above the neck",
        1, 10, RobotMapping("park", "thumb + index pressure is the gripper's squeeze while the wrist turns"),
        measure="turns"),
    "pick_place": TaskSpec(
        "pick_place", "a box grasped and placed on a plate",
        "box released with its bottom on the plate, within 3 cm of its centre", 10, 10,
        RobotMapping("park", GRIP + "; the pads close 2.5 cm below the hand's pinch (they hold the box by its sides)"),
        executable=True),
}


def task(name: str) -> TaskSpec:
    if name not in TASKS:
        raise UnknownTaskError(f"unknown task {name!r}; known tasks: {', '.join(TASKS)}")
    return TASKS[name]


# --- the success tests on trajectories ---------------------------------------------------------
def press_force(name: str, hands: np.ndarray, objects: np.ndarray, names: list[str],
                tactile: np.ndarray | None) -> np.ndarray:
    """(T,) N the task's contact presses with: from ``tactile`` (T,2,R) kPa (the glove, or a policy's
    predicted touch executed by force control) where given, else from the positions (what a
    position-controlled robot following them would press with)."""
    if name == "wiping":
        return (wiping.press_from_tactile(hands, objects, names, tactile, KPA_PER_N, TACTILE_REGIONS)
                if tactile is not None
                else wiping.press_from_positions(objects, names))
    if name == "latch":
        return (latch.press_from_tactile(hands, objects, names, tactile, KPA_PER_N, INDEX) if tactile is not None
                else latch.press_from_positions(hands, objects, names))
    if name == "bottle":
        return (bottle.grip_from_tactile(hands, objects, names, tactile, KPA_PER_N, TACTILE_REGIONS)
                if tactile is not None else bottle.grip_from_positions(hands, objects, names))
    raise UnknownTaskError(f"task {name!r} has no force-decided outcome")


def outcome(name: str, hands: np.ndarray, objects: np.ndarray, names: list[str],
            tactile: np.ndarray | None = None) -> dict:
    """The world's success test of task ``name`` over one trajectory (hands (T,2,21,3), objects
    (T,K,3), tactile (T,2,R) kPa or None); a dict with at least ``success``."""
    spec = task(name)
    if name == "wiping":
        force = press_force(name, hands, objects, names, tactile)
        return wiping.outcome(objects, names, force, contact_m=0.005 if tactile is not None else 0.0)
    if name == "latch":
        return latch.outcome(objects, names, press_force(name, hands, objects, names, tactile))
    if name == "bottle":
        return bottle.outcome(objects, names, press_force(name, hands, objects, names, tactile))
    if name == "assembly":
        return latch.outcome(objects, names, np.full(len(objects), latch.LATCH_FORCE_N)) | {"force_decides": False}
    if name == "pick_place":
        return pick_place_outcome(hands, objects, names)
    raise UnknownTaskError(f"no success test for {spec.name!r}")


def pick_place_outcome(hands: np.ndarray, objects: np.ndarray, names: list[str]) -> dict:
    bottom = objects[-1, names.index("box/bottom")]
    center = objects[-1, names.index("plate/center")]
    off = float(np.linalg.norm(bottom[:2] - center[:2]))
    on_plate = abs(float(bottom[2] - center[2])) < 0.005
    pinches = 0.5 * (hands[-1, :, 4] + hands[-1, :, 8])
    released = bool((np.linalg.norm(pinches - objects[-1, names.index("box/top")], axis=-1) > 0.03).all())
    return {"offset_mm": off * 1e3, "on_plate": bool(on_plate), "released": released,
            "success": bool(off < 0.03 and on_plate and released)}


def demo_outcome(demo: Demo) -> dict:
    """The success test on a teacher's demonstration, with the force its hands really made (the
    glove reads only one hand)."""
    m = demo.meta
    teacher = Teacher(m["task"], m["seed"], m["grasp_hand"], m["tactile_hand"])
    forces = np.array([teacher.state(i * demo.dt).forces for i in range(demo.steps)]) * KPA_PER_N
    return outcome(m["task"], demo.hands, demo.objects, demo.object_names, forces)
