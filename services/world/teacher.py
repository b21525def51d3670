"""The scripted human teacher: two hands demonstrating the thesis's tasks with randomized layouts.

Pure numpy. A demonstration is a list of waypoints per channel (pinch point of the grasping hand,
index tip of the pressing hand, yaw, aperture) joined by minimum-jerk segments, plus small
human-like variability. Objects move through a documented grasp constraint: while grasped, an
object is rigidly attached to the grasping hand's pinch frame; after insertion the board is
rigidly attached to the camera module (that is what "lifting the board by the module" verifies).

Assembly (thesis 5.8, 7.6.8): approach (objects still), precision grasp of the camera module at
the lens end, transport, place its connector on the board's connector, the other hand's index
finger presses the connector, the grasping hand lifts the module and the board comes with it.
Latch: the same, the press driven through the connector's snap (services/world/latch.py).
Pick-place (7.6.1): a box grasped from the top and set down on a plate. Wiping (7.6.2) and bottle
(7.6.3): their scripts are in services/world/wiping.py and bottle.py. The task registry with each
task's protocol and success test is services/world/tasks.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.world import bottle, latch, wiping
from services.world.hand import local_keypoints, local_to_world, pinch_shape, point_shape
from services.world.tracks import Track, rot_z, yaw_quat
from shared.demo import FINGERTIPS, HAND_NAMES, TACTILE_REGIONS, Demo

TABLE_Z = 0.0
BOARD_SIZE = (0.060, 0.030, 0.0016)  # long enough that the seated module lies on it, lens end included
CAMERA_LEN = 0.036  # lens to connector along the flex cable
GRASP_FORCE_N = 2.0
PRESS_FORCE_N = 6.0
KPA_PER_N = 10.0  # what the glove reports: force over a fingertip's ~1 cm^2
PINCH_PITCH = 0.9  # rad: fingers tilted down so the tucked fingers clear the table
PRESS_PITCH = 1.2

OBJECT_POINTS = {
    "assembly": {
        "board": {"c0": (-0.030, -0.015, 0.0016), "c1": (0.030, -0.015, 0.0016), "c2": (0.030, 0.015, 0.0016),
                  "c3": (-0.030, 0.015, 0.0016), "connector": (-0.012, 0.0, 0.0030)},
        "camera": {"lens": (0.0, 0.0, 0.004), "cable": (0.018, 0.0, 0.001), "connector": (CAMERA_LEN, 0.0, 0.0015)},
    },
    "pick_place": {
        "box": {"top": (0.0, 0.0, 0.05), "c0": (-0.025, -0.025, 0.05), "c1": (0.025, 0.025, 0.05),
                "bottom": (0.0, 0.0, 0.0)},
        "plate": {"center": (0.0, 0.0, 0.005), "c0": (-0.06, -0.06, 0.005), "c1": (0.06, 0.06, 0.005)},
    },
    "wiping": wiping.OBJECT_POINTS,
    "bottle": bottle.OBJECT_POINTS,
}
OBJECT_POINTS["latch"] = OBJECT_POINTS["assembly"]  # the assembly, its connector pressed until it latches
ASSEMBLY_TASKS = ("assembly", "latch")
TASKS = tuple(OBJECT_POINTS)


def object_names(task: str) -> list[str]:
    return [f"{obj}/{pt}" for obj, pts in OBJECT_POINTS[task].items() for pt in pts]


def sample_layout(task: str, rng: np.random.Generator) -> dict:
    """Initial placement, inside the robot's reach on the table."""
    if task in ASSEMBLY_TASKS:
        board = [rng.uniform(0.0, 0.12), rng.uniform(-0.12, -0.02), rng.uniform(-0.5, 0.5)]
        camera = [rng.uniform(-0.05, 0.08), rng.uniform(0.04, 0.14), rng.uniform(-0.6, 0.6) + np.pi]
        layout = {"board": board, "camera": camera}
        if task == "latch":
            layout["press_n"] = latch.sample_force(rng)
        return layout
    if task == "wiping":
        return wiping.sample_layout(rng)
    if task == "bottle":
        return bottle.sample_layout(rng)
    if task == "pick_place":
        return {"box": [rng.uniform(-0.1, 0.1), rng.uniform(0.05, 0.15), rng.uniform(-0.5, 0.5)],
                "plate": [rng.uniform(-0.1, 0.1), rng.uniform(-0.15, -0.05), 0.0]}
    raise ValueError(f"unknown task {task!r} (known: {', '.join(TASKS)})")


def square_pinch_yaw(hand: str) -> float:
    """Hand yaw (added to the module's) that puts the thumb-index line of the pinch at right angles to
    the module's x axis, so the fingertips sit on two opposite faces of the lens body: the grasp a
    parallel gripper makes too (the hand model's own line is 8.9 deg off at yaw 0)."""
    pts = local_to_world(hand, 0.0, PINCH_PITCH, local_keypoints(pinch_shape(), 1.0, 0.005))
    d = pts[FINGERTIPS["index"]] - pts[FINGERTIPS["thumb"]]
    off = (np.pi / 2 - np.arctan2(d[1], d[0])) % np.pi
    return float(off - np.pi if off > np.pi / 2 else off)


@dataclass
class TeacherState:
    hands: np.ndarray  # (2,21,3)
    objects: dict[str, tuple[np.ndarray, np.ndarray]]  # body -> (position, quaternion wxyz)
    keypoints: np.ndarray  # (K,3)
    forces: np.ndarray  # (2,6) N per tactile region
    phase: str


class Teacher:
    """One demonstration, evaluable at any time t in [0, duration]."""

    def __init__(self, task: str, seed: int, grasp_hand: str | None = None, tactile_hand: str | None = None) -> None:
        if task not in TASKS:
            raise ValueError(f"unknown task {task!r} (known: {', '.join(TASKS)})")
        self.task = task
        self.seed = seed
        rng = np.random.default_rng(seed)
        self.rng = rng
        self.grasp_hand = grasp_hand or ("left" if seed % 2 == 0 else "right")
        self.press_hand = "right" if self.grasp_hand == "left" else "left"
        self.tactile_hand = tactile_hand or self.grasp_hand
        self.layout = sample_layout(task, rng)
        self.names = object_names(task)
        self._local = {obj: np.array(list(pts.values())) for obj, pts in OBJECT_POINTS[task].items()}
        self._tremor = rng.normal(0, 1, (2, 6, 3))  # phases/frequencies of a slow 0.5 mm sway
        self._build(rng)

    # --- script ---------------------------------------------------------------------------
    def _build(self, rng: np.random.Generator) -> None:
        jitter = lambda scale: rng.normal(0.0, scale, 3)  # noqa: E731  (human variability)
        tempo = rng.uniform(0.9, 1.1)
        T = lambda t: t * tempo  # noqa: E731
        side = {"left": 1.0, "right": -1.0}
        g, p = self.grasp_hand, self.press_hand
        self.press_force = None  # force track (N) of the tasks whose success the force decides
        if self.task == "wiping":
            start_g = np.array([-0.12, 0.30 * side[g], 0.16]) + jitter(0.01)
            start_p = np.array([-0.15, 0.30 * side[p], 0.15]) + jitter(0.01)
            wiping.build(self, rng, T, jitter, start_g, start_p, square_pinch_yaw(g))
        elif self.task == "bottle":
            start_g = np.array([-0.12, 0.30 * side[g], 0.20]) + jitter(0.01)
            start_p = np.array([-0.15, 0.30 * side[p], 0.15]) + jitter(0.01)
            bottle.build(self, rng, T, jitter, start_g, start_p, square_pinch_yaw(g))
        elif self.task in ASSEMBLY_TASKS:
            bx, by, byaw = self.layout["board"]
            cx, cy, cyaw = self.layout["camera"]
            lens0 = np.array([cx, cy, 0.0])
            conn_local = np.array(OBJECT_POINTS["assembly"]["board"]["connector"])
            board_conn = np.array([bx, by, 0.0]) + rot_z(byaw) @ conn_local
            place_yaw = byaw + np.pi  # module lies across the board, connectors aligned
            lens_place = board_conn - rot_z(place_yaw) @ np.array([CAMERA_LEN, 0, 0]) + [0, 0, 0.0025]
            grasp_z = 0.004
            self.obj_yaw_offset = 0.0
            start_g = np.array([-0.12, 0.30 * side[g], 0.16]) + jitter(0.01)
            start_p = np.array([-0.12, 0.30 * side[p], 0.16]) + jitter(0.01)
            pin = (Track().add(0, start_g).hold(T(0.5))
                   .add(T(1.9), lens0 + [0, 0, 0.05] + jitter(0.003))
                   .add(T(2.5), lens0 + [0, 0, grasp_z]).hold(T(2.9))
                   .add(T(3.5), lens0 + [0, 0, 0.06])
                   .add(T(4.5), lens_place + [0, 0, 0.02] + jitter(0.002))
                   .add(T(5.0), lens_place).hold(T(6.5))
                   .add(T(7.4), lens_place + [0, 0, 0.05]).hold(T(8.0)))
            tip = (Track().add(0, start_p).hold(T(0.5))
                   .add(T(2.2), board_conn + [-0.05, 0.04 * side[p], 0.08] + jitter(0.005)).hold(T(5.0))
                   .add(T(5.4), board_conn + [0, 0, 0.012])
                   .add(T(5.8), board_conn + [0, 0, 0.0045]).hold(T(6.1))
                   .add(T(6.5), board_conn + [-0.04, 0.03 * side[p], 0.07])
                   .add(T(8.0), start_p))
            if self.task == "latch":  # down onto the connector and through its snap
                tip, self.press_force, self.press_window = latch.press_tracks(
                    T, board_conn, tip.values[2], tip.values[7], start_p, self.layout["press_n"])
            square = square_pinch_yaw(g)  # thumb-index line across the lens body's faces
            self.pinch_yaw = Track().add(0, 0.0).hold(T(0.5)).add(T(2.4), cyaw + square).hold(T(3.5)) \
                .add(T(4.6), place_yaw + square).hold(T(8.0))
            self.press_yaw = Track().add(0, 0.0).hold(T(1.0)).add(T(2.2), byaw * 0.5).hold(T(8.0))
            self.aperture = Track().add(0, 0.04).hold(T(2.0)).add(T(2.5), 0.025).add(T(2.9), 0.005).hold(T(6.5)) \
                .hold(T(8.0))
            self.opposition = Track().add(0, 0.2).add(T(1.8), 1.0).hold(T(8.0))
            self.phases = [(0.0, "approach"), (T(2.5), "grasp"), (T(3.0), "transport"), (T(4.6), "place"),
                           (T(5.2), "press"), (T(6.3), "lift"), (T(7.5), "done")]
            self.grasp_window = (T(2.9), np.inf)
            if self.task != "latch":
                self.press_window = (T(5.6), T(6.2))
            self.insert_time = T(6.1)
            self.lens0, self.cyaw, self.board0, self.byaw = lens0, cyaw, np.array([bx, by, 0.0]), byaw
            self.duration = T(8.0)
        else:  # pick_place
            bx, by, byaw = self.layout["box"]
            px, py, _ = self.layout["plate"]
            top0 = np.array([bx, by, 0.05])
            target = np.array([px, py, 0.055])
            start_g = np.array([-0.12, 0.30 * side[g], 0.18]) + jitter(0.01)
            start_p = np.array([-0.15, 0.30 * side[p], 0.15]) + jitter(0.01)
            pin = (Track().add(0, start_g).hold(T(0.5)).add(T(1.8), top0 + [0, 0, 0.05]).add(T(2.3), top0)
                   .hold(T(2.7)).add(T(3.3), top0 + [0, 0, 0.08]).add(T(4.5), target + [0, 0, 0.03])
                   .add(T(5.0), target).hold(T(5.4)).add(T(6.2), target + [0, 0, 0.1]).hold(T(7.0)))
            tip = Track().add(0, start_p).hold(T(7.0))
            self.pinch_yaw = Track().add(0, 0.0).add(T(2.0), byaw).hold(T(7.0))
            self.press_yaw = Track().add(0, 0.0).hold(T(7.0))
            self.aperture = Track().add(0, 0.07).hold(T(2.3)).add(T(2.7), 0.05).hold(T(5.2)).add(T(5.6), 0.08) \
                .hold(T(7.0))
            self.opposition = Track().add(0, 0.3).add(T(1.8), 1.0).hold(T(7.0))
            self.phases = [(0.0, "approach"), (T(2.3), "grasp"), (T(3.0), "transport"), (T(5.0), "place"),
                           (T(5.6), "retreat"), (T(6.5), "done")]
            self.grasp_window = (T(2.7), T(5.4))
            self.press_window = (np.inf, np.inf)
            self.insert_time = np.inf
            self.top0, self.byaw, self.plate = top0, byaw, np.array([px, py, 0.0])
            self.duration = T(7.0)
        if self.task not in ("wiping", "bottle"):  # their build sets their own
            self.pinch, self.tip = pin, tip

    # --- evaluation -------------------------------------------------------------------------
    def phase(self, t: float) -> str:
        current = self.phases[0][1]
        for start, name in self.phases:
            if t >= start:
                current = name
        return current

    def _sway(self, hand: int, t: float) -> np.ndarray:
        a = self._tremor[hand]
        return 0.0005 * np.sin(t * (0.7 + np.abs(a[0])) + a[1])

    def _hands(self, t: float) -> np.ndarray:
        hands = np.zeros((2, 21, 3))
        gi, pi = HAND_NAMES.index(self.grasp_hand), HAND_NAMES.index(self.press_hand)
        # Grasping hand: placed so the thumb-index midpoint is at the pinch point.
        local = local_keypoints(pinch_shape(), float(self.opposition(t)[0]), float(self.aperture(t)[0]))
        placed = local_to_world(self.grasp_hand, float(self.pinch_yaw(t)[0]), PINCH_PITCH, local)
        target = self.pinch(t) + self._sway(gi, t)
        hands[gi] = placed - 0.5 * (placed[4] + placed[8]) + target
        # Pressing hand: index tip at the tip track, fingers pointing down.
        curl, opp = point_shape()
        placed_p = local_to_world(self.press_hand, float(self.press_yaw(t)[0]), PRESS_PITCH,
                                  local_keypoints(curl, opp, 0.03))
        hands[pi] = placed_p - placed_p[FINGERTIPS["index"]] + self.tip(t) + self._sway(pi, t)
        return hands

    def _objects(self, t: float, hands: np.ndarray) -> dict[str, tuple[np.ndarray, float]]:
        """Object origin and yaw. The grasp constraint: rigid to the pinch frame while grasped."""
        gi = HAND_NAMES.index(self.grasp_hand)
        pinch_now = 0.5 * (hands[gi, 4] + hands[gi, 8])
        grasped = self.grasp_window[0] <= t < self.grasp_window[1]
        if self.task == "wiping":
            return wiping.objects(self, t, pinch_now)
        if self.task == "bottle":
            return bottle.objects(self, t, pinch_now)
        if self.task in ASSEMBLY_TASKS:
            if grasped:
                cam_pos = pinch_now - [0, 0, 0.004] + [0, 0, 0]
                cam_yaw = float(self.pinch_yaw(t)[0]) - float(self.pinch_yaw(self.grasp_window[0])[0]) + self.cyaw
            else:
                cam_pos, cam_yaw = self.lens0.copy(), self.cyaw
            board_pos, board_yaw = self.board0.copy(), self.byaw
            if t >= self.insert_time:  # inserted: the board hangs from the module
                ref = self._objects_at_insert
                board_pos = cam_pos + rot_z(cam_yaw - ref[1]) @ (self.board0 - ref[0])
                board_pos[2] = max(board_pos[2], 0.0)
                board_yaw = self.byaw + cam_yaw - ref[1]
            return {"board": (board_pos, board_yaw), "camera": (cam_pos, cam_yaw)}
        box_yaw0 = self.byaw
        if grasped:
            box_pos = pinch_now - [0, 0, 0.05]
            box_yaw = box_yaw0 + float(self.pinch_yaw(t)[0]) - float(self.pinch_yaw(self.grasp_window[0])[0])
        elif t >= self.grasp_window[1]:
            end = self._hands(self.grasp_window[1] - 1e-6)
            box_pos = 0.5 * (end[gi, 4] + end[gi, 8]) - [0, 0, 0.05]
            box_yaw = box_yaw0
        else:
            box_pos, box_yaw = self.top0 - [0, 0, 0.05], box_yaw0
        return {"box": (box_pos, box_yaw), "plate": (self.plate.copy(), 0.0)}

    @property
    def _objects_at_insert(self) -> tuple[np.ndarray, float]:
        if not hasattr(self, "_insert_ref"):
            hands = self._hands(self.insert_time - 1e-6)
            gi = HAND_NAMES.index(self.grasp_hand)
            pinch = 0.5 * (hands[gi, 4] + hands[gi, 8])
            turn = float(self.pinch_yaw(self.insert_time)[0]) - float(self.pinch_yaw(self.grasp_window[0])[0])
            yaw = turn + self.cyaw
            self._insert_ref = (pinch - [0, 0, 0.004], yaw)
        return self._insert_ref

    def _forces(self, t: float) -> np.ndarray:
        forces = np.zeros((2, len(TACTILE_REGIONS)))
        gi, pi = HAND_NAMES.index(self.grasp_hand), HAND_NAMES.index(self.press_hand)
        if self.task == "wiping":
            return wiping.forces(self, t, TACTILE_REGIONS, gi)
        if self.task == "bottle":
            return bottle.forces(self, t, TACTILE_REGIONS, gi, pi)
        g0, g1 = self.grasp_window
        if g0 - 0.3 <= t < g1 + 0.2:  # ramps as the fingers close and open
            ramp = min(1.0, (t - (g0 - 0.3)) / 0.3) * (1.0 if t < g1 else max(0.0, 1 - (t - g1) / 0.2))
            lift_extra = 1.5 if self.phase(t) in ("lift", "done") and self.task in ASSEMBLY_TASKS else 1.0
            forces[gi, TACTILE_REGIONS.index("thumb")] = GRASP_FORCE_N * ramp * lift_extra
            forces[gi, TACTILE_REGIONS.index("index")] = GRASP_FORCE_N * ramp * lift_extra
        p0, p1 = self.press_window
        if self.press_force is not None:
            forces[pi, TACTILE_REGIONS.index("index")] = float(self.press_force(t)[0])
        elif p0 - 0.2 <= t < p1 + 0.2:
            ramp = np.clip(min((t - (p0 - 0.2)) / 0.2, (p1 + 0.2 - t) / 0.2), 0.0, 1.0)
            forces[pi, TACTILE_REGIONS.index("index")] = PRESS_FORCE_N * ramp
        return forces

    def state(self, t: float) -> TeacherState:
        hands = self._hands(t)
        objects = self._objects(t, hands)
        keypoints = np.concatenate([pos + self._local[obj] @ rot_z(yaw).T for obj, (pos, yaw) in objects.items()])
        return TeacherState(hands, {k: (pos, yaw_quat(yaw)) for k, (pos, yaw) in objects.items()}, keypoints,
                            self._forces(t), self.phase(t))


def occlusion(hands: np.ndarray, objects: np.ndarray, radius: float = 0.012) -> tuple[np.ndarray, np.ndarray]:
    """Visibility heuristic for a rig looking down from above: a point is hidden when a hand keypoint
    of the other hand or of a different finger lies within ``radius`` horizontally and >1 cm above it."""
    pts = np.concatenate([hands.reshape(-1, 3), objects])
    hand_pts = hands.reshape(-1, 3)
    d_xy = np.linalg.norm(pts[:, None, :2] - hand_pts[None, :, :2], axis=-1)
    above = hand_pts[None, :, 2] > pts[:, None, 2] + 0.01
    finger = np.arange(42) % 21
    chain = np.where(finger == 0, -1, (finger - 1) // 4)
    owner = np.concatenate([np.arange(42) // 21 * 10 + chain, np.full(len(objects), -99)])
    other_chain = owner[:, None] != (np.arange(42) // 21 * 10 + chain)[None, :]
    hidden = ((d_xy < radius) & above & other_chain).any(axis=1)
    visible = (~hidden).astype(np.uint8)
    return visible[:42].reshape(2, 21), visible[42:]


def generate_demo(task: str, seed: int, tactile_hand: str | None = None, grasp_hand: str | None = None,
                  dt: float = 0.02, index: int = 0) -> Demo:
    teacher = Teacher(task, seed, grasp_hand, tactile_hand)
    times = np.arange(0.0, teacher.duration + 1e-9, dt)
    hands, objs, forces, hmask, omask, phases = [], [], [], [], [], []
    for t in times:
        st = teacher.state(float(t))
        hands.append(st.hands)
        objs.append(st.keypoints)
        forces.append(st.forces)
        hv, ov = occlusion(st.hands, st.keypoints)
        hmask.append(hv)
        omask.append(ov)
        phases.append(st.phase)
    tactile_mask = np.zeros((len(times), 2, len(TACTILE_REGIONS)), np.uint8)
    tactile_mask[:, HAND_NAMES.index(teacher.tactile_hand)] = 1
    forces = np.array(forces, np.float32)
    # What the glove reports: region pressure in kPa (force over a fingertip's ~1 cm^2), gloved hand only.
    tactile = forces * KPA_PER_N * tactile_mask
    return Demo(dt=dt, hands=np.array(hands, np.float32), hand_mask=np.array(hmask, np.uint8),
                object_names=teacher.names, objects=np.array(objs, np.float32), object_mask=np.array(omask, np.uint8),
                tactile=tactile.astype(np.float32), tactile_mask=tactile_mask, phase=phases,
                meta={"task": task, "seed": seed, "demo": index, "grasp_hand": teacher.grasp_hand,
                      "press_hand": teacher.press_hand, "tactile_hand": teacher.tactile_hand,
                      "layout": teacher.layout})


def assembly_protocol(seed: int) -> list[Demo]:
    """The 15 demonstrations of thesis 7.6.8: 3 train + 12 validation, hands swapped between demos.

    Train: two with the glove on the grasping hand, one with the glove on the pressing hand.
    """
    demos = []
    for i in range(15):
        grasp = "left" if i % 2 == 0 else "right"
        press = "right" if grasp == "left" else "left"
        tactile = press if i == 2 else grasp
        d = generate_demo("assembly", seed * 1000 + i, tactile_hand=tactile, grasp_hand=grasp, index=i)
        d.meta["split"] = "train" if i < 3 else "validation"
        demos.append(d)
    return demos
