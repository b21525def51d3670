"""WorldSim: MuJoCo physics + the scripted teacher, without any I/O (the service wraps it).

Two modes. "teacher": the teacher's hands demonstrate, the objects follow the teacher's grasp
constraint (their free joints are set from the script every step), demonstrations follow one
another with new layouts. "robot": the hands leave, objects are physical, the robot acts.
"""

from __future__ import annotations

import mujoco
import numpy as np

from services.world import latch, wiping
from services.world.model import ASSEMBLY_TASKS, LATCH, PHYSICS_DT, build_model, camera_specs
from services.world.teacher import OBJECT_POINTS, Teacher, occlusion
from shared.demo import HAND_NAMES, TACTILE_REGIONS
from shared.kinematics import load_robot
from shared.robots.registry import DEFAULT_ROBOT, describe

PAUSE_BETWEEN_DEMOS_S = 1.0
TEACHER_DT = 0.01  # the script is evaluated at 100 Hz; physics runs at 500 Hz
SEAT_GAP_M = 0.003  # module connector this close to the board's: aligned (the success test uses it too)
SEAT_FORCE_N = 2.0  # module-on-board normal force that snaps an aligned connector home (robot mode)
# the latch task's snap-fit needs the press of services/world/latch.py
SEAT_FORCE_BY_TASK = {"assembly": SEAT_FORCE_N, "latch": latch.LATCH_FORCE_N}
WIPE_CHECK_EVERY = 5  # physics steps between updates of the wiping test (10 ms)


class WorldSim:
    def __init__(self, task: str = "assembly", seed: int = 0, width: int = 320, height: int = 240,
                 robot: str = DEFAULT_ROBOT) -> None:
        self.task = task
        self.base_seed = seed
        self.width, self.height = width, height
        self.robot_name = robot
        self.model = build_model(task, width, height, robot)
        self.model.opt.timestep = PHYSICS_DT
        self.data = mujoco.MjData(self.model)
        self.robot = load_robot(robot)
        self.joint_names = self.robot.joint_names
        m = self.model
        self._qadr = np.array([m.jnt_qposadr[m.joint(n).id] for n in self.joint_names])
        home = describe(robot).home
        self._home = self.robot.couple(np.array([home.get(n, 0.0) for n in self.joint_names])) if home else None
        self._dadr = np.array([m.jnt_dofadr[m.joint(n).id] for n in self.joint_names])
        self._act = {m.actuator(i).name: i for i in range(m.nu)}
        self._act_index = [self._act.get(n, -1) for n in self.joint_names]
        self._bodies = [name for name in OBJECT_POINTS[task] if _has_body(m, name)]  # the teacher's order
        self._free = {b: m.jnt_qposadr[m.joint(f"{b}_free").id] for b in self._bodies}
        self._free_dof = {b: m.jnt_dofadr[m.joint(f"{b}_free").id] for b in self._bodies}
        self._mocap = np.array([[m.body_mocapid[m.body(f"{h}_kp{k}").id] for k in range(21)] for h in HAND_NAMES])
        snap_fit = task in ASSEMBLY_TASKS
        self._latch = m.equality(LATCH).id if snap_fit else None
        self._seat_force_n = SEAT_FORCE_BY_TASK.get(task, SEAT_FORCE_N)
        self._seat_bodies = {m.body("camera").id, m.body("board").id} if snap_fit else set()
        self._connectors = [(m.body(b).id, np.array(OBJECT_POINTS["assembly"][b]["connector"]))
                            for b in ("camera", "board")] if snap_fit else []
        self._wipe_bodies = {m.body("sponge").id, m.body("plate").id} if task == "wiping" else set()
        self.wipe_monitor = wiping.WipeMonitor()  # the wiping test in robot mode
        self._steps = 0
        self.seated_at: float | None = None  # simulated time the connector snapped home (robot mode)
        self.robot_mode = "teacher"
        self.demo = 0
        self.reset(seed)

    # --- lifecycle ----------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> None:
        if seed is not None:
            self.base_seed = seed
        mujoco.mj_resetData(self.model, self.data)
        if self._home is not None:
            self.data.qpos[self._qadr] = self._home
        self.demo = 0
        self._start_demo()
        mujoco.mj_forward(self.model, self.data)

    def start_demo(self, index: int) -> None:
        """Jumps to demonstration ``index`` of this seed's sequence (its layout and hands)."""
        self.demo = int(index)
        self._start_demo()
        mujoco.mj_forward(self.model, self.data)

    def _start_demo(self) -> None:
        grasp = "left" if self.demo % 2 == 0 else "right"
        tactile = grasp if self.demo % 3 != 2 else ("right" if grasp == "left" else "left")
        self.teacher = Teacher(self.task, self.base_seed * 1000 + self.demo, grasp_hand=grasp, tactile_hand=tactile)
        self.demo_start = float(self.data.time)
        self._applied_at = 0.0
        self._engage_latch(False)
        self._apply_teacher(0.0)

    @property
    def physics_dt(self) -> float:
        return float(self.model.opt.timestep)

    @property
    def time(self) -> float:
        return float(self.data.time)

    def demo_time(self) -> float:
        return self.time - self.demo_start

    # --- stepping -----------------------------------------------------------------------
    def step(self, n: int = 1) -> None:
        for _ in range(n):
            if self.robot_mode == "teacher":
                t = self.demo_time()
                if t > self.teacher.duration + PAUSE_BETWEEN_DEMOS_S:
                    self.demo += 1
                    self._start_demo()
                    t = 0.0
                if t - self._applied_at >= TEACHER_DT - 1e-9 or t < self._applied_at:
                    self._apply_teacher(min(t, self.teacher.duration))
                    self._applied_at = t
                else:
                    self._hold_objects()
            mujoco.mj_step(self.model, self.data)
            if self.robot_mode == "robot" and self._latch is not None and self.seated_at is None:
                self._check_seat()
            self._steps += 1
            if self.robot_mode == "robot" and self._wipe_bodies and self._steps % WIPE_CHECK_EVERY == 0:
                names, pts = self.object_keypoints()
                self.wipe_monitor.update(pts, names, self._contact_force(self._wipe_bodies))

    # --- the connector's snap-fit (robot mode) -----------------------------------------------
    def connector_gap(self) -> float:
        """Distance between the module's connector and the board's (m)."""
        (cam, c_local), (board, b_local) = self._connectors
        c = self.data.xmat[cam].reshape(3, 3) @ c_local + self.data.xpos[cam]
        b = self.data.xmat[board].reshape(3, 3) @ b_local + self.data.xpos[board]
        return float(np.linalg.norm(c - b))

    def _seat_force(self) -> float:
        """Total normal force between the module and the board (N)."""
        return self._contact_force(self._seat_bodies)

    def _contact_force(self, bodies: set[int]) -> float:
        """Total normal force between the two ``bodies`` (N)."""
        total, f6 = 0.0, np.zeros(6)
        for i in range(self.data.ncon):
            c = self.data.contact[i]
            if {self.model.geom_bodyid[c.geom1], self.model.geom_bodyid[c.geom2]} == bodies:
                mujoco.mj_contactForce(self.model, self.data, i, f6)
                total += abs(f6[0])
        return total

    def _check_seat(self) -> None:
        if self.connector_gap() < SEAT_GAP_M and self._seat_force() >= self._seat_force_n:
            self._engage_latch(True)

    def _engage_latch(self, on: bool) -> None:
        """Welds the board to the module where they are now (on) or releases it."""
        if self._latch is None:
            return
        if on:
            # weld data: anchor (3), pose of body2 (the board) in body1's (the module's) frame (3 + 4)
            cam, board = self.model.body("camera").id, self.model.body("board").id
            R_cam = self.data.xmat[cam].reshape(3, 3)
            rel_pos = R_cam.T @ (self.data.xpos[board] - self.data.xpos[cam])
            rel_quat, inv = np.zeros(4), np.zeros(4)
            mujoco.mju_negQuat(inv, self.data.xquat[cam])
            mujoco.mju_mulQuat(rel_quat, inv, self.data.xquat[board])
            self.model.eq_data[self._latch, 0:3] = 0.0
            self.model.eq_data[self._latch, 3:6] = rel_pos
            self.model.eq_data[self._latch, 6:10] = rel_quat
            self.seated_at = self.time
        else:
            self.seated_at = None
        self.data.eq_active[self._latch] = int(on)

    def _apply_teacher(self, t: float) -> None:
        state = self.teacher.state(t)
        self._teacher_state = state
        self.data.mocap_pos[self._mocap.ravel()] = state.hands.reshape(-1, 3)
        self._hold_objects()

    def _hold_objects(self) -> None:
        """The grasp constraint: objects sit where the script puts them."""
        for body, (pos, quat) in self._teacher_state.objects.items():
            adr, dof = self._free[body], self._free_dof[body]
            self.data.qpos[adr:adr + 3] = pos
            self.data.qpos[adr + 3:adr + 7] = quat
            self.data.qvel[dof:dof + 6] = 0.0

    def set_robot_mode(self, mode: str) -> None:
        if mode not in ("teacher", "robot"):
            raise ValueError(f"mode must be 'teacher' or 'robot', got {mode!r}")
        self.robot_mode = mode
        self.wipe_monitor = wiping.WipeMonitor()
        if mode == "robot":
            self.data.mocap_pos[self._mocap.ravel()] = [0.0, 0.0, -1.0]  # hands leave the cell

    # --- robot I/O ----------------------------------------------------------------------
    def joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        return self.data.qpos[self._qadr].copy(), self.data.qvel[self._dadr].copy()

    def set_efforts(self, efforts: np.ndarray) -> None:
        for i, a in enumerate(self._act_index):
            if a >= 0:
                self.data.ctrl[a] = efforts[i]

    # --- observations (truth) -----------------------------------------------------------
    def hand_keypoints(self) -> np.ndarray:
        if self.robot_mode == "robot":
            return np.zeros((2, 21, 3))
        return self._teacher_state.hands.copy()

    def object_keypoints(self) -> tuple[list[str], np.ndarray]:
        names, points = [], []
        for body in self._bodies:
            bid = self.model.body(body).id
            R = self.data.xmat[bid].reshape(3, 3)
            points.append(self.teacher._local[body] @ R.T + self.data.xpos[bid])
            names += [n for n in self.teacher.names if n.startswith(body + "/")]
        return names, np.concatenate(points)

    def visibility(self) -> tuple[np.ndarray, np.ndarray]:
        _, objects = self.object_keypoints()
        return occlusion(self.hand_keypoints(), objects)

    def body_poses(self) -> dict[str, np.ndarray]:
        return {b: np.concatenate([self.data.xpos[self.model.body(b).id], self.data.xquat[self.model.body(b).id]])
                for b in self._bodies}

    def region_forces(self) -> np.ndarray:
        if self.robot_mode == "robot":
            return np.zeros((2, len(TACTILE_REGIONS)))
        return self._teacher_state.forces.copy()

    def session(self) -> dict:
        phase = self._teacher_state.phase if self.demo_time() <= self.teacher.duration else "done"
        return {"task": self.task, "demo": self.demo, "phase": phase if self.robot_mode == "teacher" else "robot",
                "tactile_hand": self.teacher.tactile_hand, "grasp_hand": self.teacher.grasp_hand,
                "layout": self.teacher.layout}

    def camera_specs(self):
        return camera_specs(self.width, self.height)

    def task_success(self) -> dict:
        """The task's success test on the physical world (robot mode), with its measurements."""
        if self.task in ASSEMBLY_TASKS:  # latch: the snap engages only at its force (SEAT_FORCE_BY_TASK)
            return {"success": self.assembly_success(), "seated": self.seated_at is not None,
                    "connector_gap_mm": self.connector_gap() * 1e3}
        if self.task == "wiping":
            return self.wipe_monitor.result()
        if self.task == "bottle":  # the cap's thread is not modelled in MuJoCo: no physical test
            return {"success": False, "checked": False}
        names, pts = self.object_keypoints()  # pick_place: the box resting on the plate
        bottom, center = pts[names.index("box/bottom")], pts[names.index("plate/center")]
        off = float(np.linalg.norm(bottom[:2] - center[:2]))
        return {"offset_mm": off * 1e3, "success": bool(off < 0.03 and abs(bottom[2] - center[2]) < 0.005)}

    def assembly_success(self) -> bool:
        """Camera module seated on the board's connector and the board lifted off the table."""
        if self.task not in ASSEMBLY_TASKS:
            return False
        names, pts = self.object_keypoints()
        board_z = min(pts[names.index(f"board/c{i}")][2] for i in range(4))
        return bool(self.connector_gap() < SEAT_GAP_M and board_z > 0.02)


def _has_body(model: mujoco.MjModel, name: str) -> bool:
    try:
        model.body(name)
        return True
    except KeyError:
        return False

