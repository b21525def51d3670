"""world node: the simulated workcell in real time.

Steps MuJoCo with the scripted teacher, hosts the simulated devices (two glove readout modules
and the robot control board as ptys speaking the real protocols), publishes simulated time,
ground truth (evaluation only) and the session label, and renders the camera rig on request.
"""

from __future__ import annotations

import asyncio
import json
import time
from dataclasses import dataclass

import numpy as np

from services.robot.safety import board_limits
from services.world import calibration_sequence as calseq
from services.world.devices import BoardDevice, GloveDevice
from services.world.model import CALIB_BOARD
from services.world.render import snapshot
from services.world.sim import WorldSim
from shared import msgs
from shared.charuco import BoardSpec
from shared.demo import HAND_NAMES
from shared.realtime import raise_cpu_share, thread_schedstat
from shared.robots.registry import DEFAULT_ROBOT, describe
from shared.runtime import Node

SNAPSHOT_KEY = "xm/world/sim/@snapshot"
WIRE_WAIT_S = 0.0005  # how often a step held back for the robot's pty asks again


class GapMeter:
    """Pure: the longest wall-time gap between two clock messages, how long after the first one it
    began, and how much of it the world's thread spent runnable but waiting for a CPU (the kernel's
    run delay): a world starved by the host shows here, one that stalled itself does not."""

    def __init__(self) -> None:
        self.first: float | None = None
        self.last: tuple[float, float] | None = None  # (wall, cumulative run delay)
        self.longest = (0.0, 0.0, 0.0)  # (gap, began after first, waited for a CPU)

    def sent(self, now: float, run_delay: float) -> None:
        if self.last is None:
            self.first = now
        elif now - self.last[0] > self.longest[0]:
            self.longest = (now - self.last[0], self.last[0] - self.first, run_delay - self.last[1])
        self.last = (now, run_delay)

    def stats(self) -> dict:
        gap, began, waited = self.longest
        return {"longest_s": round(gap, 4), "began_after_s": round(began, 3), "waited_for_cpu_s": round(waited, 4)}


class WorldService:
    @dataclass
    class Params:
        task: str = "assembly"
        robot: str = DEFAULT_ROBOT  # a described robot (shared/robots/registry.py)
        seed: int = 0
        realtime_factor: float = 1.0
        glove_ports: tuple[str, ...] = ()
        robot_port: str = ""
        glove_rate_hz: float = 100.0
        truth_rate_hz: float = 50.0
        clock_rate_hz: float = 100.0
        tick_s: float = 0.006
        # The world stands in for physics, which never waits for a CPU: on a busy host it runs this many
        # nice values ahead of the services, whose schedules all follow its clock.
        cpu_share_boost: int = 5

    def __init__(self, node: Node, params: Params) -> None:
        self.node = node
        self.p = params
        self.sim = WorldSim(task=params.task, seed=params.seed, robot=params.robot)
        self.physics_dt = float(self.sim.model.opt.timestep)
        self.substeps = max(1, round(params.tick_s / self.physics_dt))
        self.gloves = [GloveDevice(port, hand, seed=i, rate_hz=params.glove_rate_hz)  # seed i: its calibration
                       for i, (hand, port) in enumerate(zip(HAND_NAMES, params.glove_ports, strict=False))]
        self.board = (BoardDevice(params.robot_port, describe(params.robot).board_order, board_limits(self.sim.robot))
                      if params.robot_port else None)
        self._wall0, self._sim0 = time.monotonic(), 0.0  # the pacing map, wall -> simulated time
        self.clock_pub = node.output("clock")
        self.truth_pub = node.output("truth")
        self.session_pub = node.output("session")
        self._snapshot_q = node.session.declare_queryable(SNAPSHOT_KEY, self._on_snapshot)
        self._last_session: tuple | None = None
        self._due = {"clock": 0.0, "truth": 0.0, "session": 0.0}
        self._repace = False  # set by a reset: pace real time from the new simulated time
        self._clock_gaps = GapMeter()
        node.queryable("reset", self.cmd_reset)
        node.queryable("mode", self.cmd_mode)
        node.queryable("outcome", self.cmd_outcome)
        node.queryable("calibration", self.cmd_calibration)
        self._board_mocap = int(self.sim.model.body_mocapid[self.sim.model.body(CALIB_BOARD).id])
        self._calib_key: tuple | None = None
        self._calib_poses: list[np.ndarray] = []
        node.health_extra = self._health
        if params.cpu_share_boost > 0:
            raise_cpu_share("world", node.log, params.cpu_share_boost)

    # --- control queryables -------------------------------------------------------------
    def cmd_reset(self, req: dict) -> dict:
        seed = int(req.get("seed", self.p.seed))
        self.sim.reset(seed)
        # Simulated time restarts at 0: every schedule on the old timeline starts over.
        self._due = dict.fromkeys(self._due, 0.0)
        for glove in self.gloves:
            glove.restart_schedule()
        if self.board is not None:
            self.board.restart_schedule()
        self._repace = True
        return {"ok": True, "seed": seed}

    def cmd_mode(self, req: dict) -> dict:
        mode = req.get("mode")
        if mode not in ("teacher", "robot"):
            return {"ok": False, "error": f"mode must be 'teacher' or 'robot', got {mode!r}"}
        self.sim.set_robot_mode(mode)  # robot: the teacher's hands leave the cell, the task's test starts over
        return {"ok": True, "mode": mode}

    def cmd_outcome(self, req: dict) -> dict:
        """The task's success test on the physical world now, with its measurements (the dashboard's
        executions log it); meaningful in robot mode, after the robot has acted."""
        return {"ok": True, "task": self.sim.task, "mode": self.sim.robot_mode, "sim_time": self.sim.time,
                **self.sim.task_success()}

    def cmd_calibration(self, req: dict) -> dict:
        """Place the calibration board at pose ``index`` of the sequence (``count``, ``seed``,
        ``registration``), or ``{"hide": true}``; answers the sim time from which frames show it."""
        board = BoardSpec()
        if req.get("hide"):
            self.sim.data.mocap_pos[self._board_mocap] = [0.0, 0.0, calseq.HIDDEN_Z]
            return {"ok": True, "hidden": True, "time": self.sim.time, "board": board.to_dict()}
        try:
            count, seed, index = int(req.get("count", 120)), int(req.get("seed", 0)), int(req["index"])
            reg = calseq.Registration.from_dict(req.get("registration", {}))
            key = (count, seed, reg)
            if key != self._calib_key:
                self._calib_poses, self._calib_key = calseq.sequence(board, count, seed, reg), key
            if not 0 <= index < count:
                raise ValueError(f"index {index} outside the sequence of {count} poses")
        except (KeyError, TypeError, ValueError) as exc:
            self.node.stats.count("bad_calibration_request")
            return {"ok": False, "error": f"calibration: {exc!r}; send {{\"index\": i, \"count\": n, \"seed\": s}} "
                                          "or {\"hide\": true}"}
        pose = self._calib_poses[index]
        pos, quat = calseq.mocap(pose)
        self.sim.data.mocap_pos[self._board_mocap] = pos
        self.sim.data.mocap_quat[self._board_mocap] = quat
        return {"ok": True, "index": index, "count": count, "time": self.sim.time, "world_T_board": pose.tolist(),
                "board": board.to_dict()}

    def _health(self) -> dict:
        return {"sim_time": self.sim.time, "realtime_ratio": round(self._rt_ratio, 3),
                "clock_gap": self._clock_gaps.stats(),
                "devices": {**{f"glove/{g.hand}": g.stats() for g in self.gloves},
                            **({"robot": self.board.stats()} if self.board else {})}}

    # --- camera rig ---------------------------------------------------------------------
    def _on_snapshot(self, query) -> None:  # Zenoh thread: the loop takes the snapshot between steps
        self.node.loop.call_soon_threadsafe(self._answer_snapshot, query)

    def _answer_snapshot(self, query) -> None:
        try:
            sim = self.sim
            snap = snapshot(sim.task, sim.data, sim.robot_name, sim.base_seed, sim.demo,
                            sim.teacher.tactile_hand if sim.robot_mode == "teacher" else "")
            query.reply(SNAPSHOT_KEY, snap.to_json())
        finally:
            query.drop()

    # --- main loop ----------------------------------------------------------------------
    def _sim_time_of(self, wall: float) -> float:
        """The simulated time a wall time (monotonic) maps to, one tick ahead: a burst simulates the
        tick after the wall time it runs at, so what arrived during the last sleep belongs into it."""
        return self._sim0 + (wall - self._wall0) * self.p.realtime_factor + self.p.tick_s

    async def run(self) -> None:
        self._rt_ratio = 0.0
        wall0, sim0 = time.monotonic(), self.sim.time
        while True:
            self._wall0, self._sim0 = wall0, sim0
            for _ in range(self.substeps):
                # The board's clock waits for a command the pty may still hold (BoardDevice.step).
                while self.board is not None and not self.board.step(self.sim, self._sim_time_of):
                    await asyncio.sleep(WIRE_WAIT_S)
                self.sim.step(1)
            self._publish_due()
            if self._repace:
                self._repace, wall0, sim0 = False, time.monotonic(), self.sim.time
            # Pace to real time (scaled); if we fall behind, run flat out and report the ratio.
            sim_elapsed = self.sim.time - sim0
            wall_target = wall0 + sim_elapsed / self.p.realtime_factor
            now = time.monotonic()
            self._rt_ratio = sim_elapsed / max(now - wall0, 1e-9)
            if wall_target > now:
                await asyncio.sleep(wall_target - now)
            else:
                await asyncio.sleep(0)
                if now - wall_target > 1.0:  # far behind: stop trying to catch up
                    wall0, sim0 = now, self.sim.time

    def _publish_due(self) -> None:
        t = self.sim.time
        due = self._due
        if t >= due["clock"]:
            due["clock"] = t + 1.0 / self.p.clock_rate_hz - 1e-9
            self.clock_pub.put(msgs.make("rosgraph_msgs/msg/Clock", clock=msgs.stamp(t)))
            self._clock_gaps.sent(time.monotonic(), thread_schedstat()[0])
        forces = hands = None
        for i, glove in enumerate(self.gloves):  # each module at its own registers' frame period
            if glove.due(t):
                if forces is None:
                    forces, hands = self.sim.region_forces(), self.sim.hand_keypoints()
                glove.emit(t, forces[i], hands[i])
            else:
                glove.poll()
        if t >= due["truth"]:
            due["truth"] = t + 1.0 / self.p.truth_rate_hz - 1e-9
            self.truth_pub.put(self._truth(t))
        session = self.sim.session()
        key = (session["demo"], session["phase"])
        if t >= due["session"] or key != self._last_session:
            due["session"] = t + 1.0 - 1e-9
            self._last_session = key
            self.session_pub.put(msgs.make(
                "xm_msgs/msg/Session", header=msgs.header(t, "world"), task=session["task"],
                demo=int(session["demo"]), phase=session["phase"], tactile_hand=session["tactile_hand"],
                seed_layout=json.dumps(session.get("layout", {}), default=float)))

    def _truth(self, t: float):
        hands = np.asarray(self.sim.hand_keypoints(), np.float32)
        names, objects = self.sim.object_keypoints()
        hand_vis, obj_vis = self.sim.visibility()
        bodies = self.sim.body_poses()
        return msgs.make(
            "xm_msgs/msg/GroundTruth", header=msgs.header(t, "world"), hand_names=list(HAND_NAMES),
            hand_keypoints=hands.ravel(), hand_visible=np.asarray(hand_vis, np.uint8).ravel(),
            object_names=list(names), object_keypoints=np.asarray(objects, np.float32).ravel(),
            object_visible=np.asarray(obj_vis, np.uint8).ravel(), body_names=list(bodies),
            body_poses=np.asarray(list(bodies.values()), np.float32).ravel(),
            contact_forces=np.asarray(self.sim.region_forces(), np.float32).ravel())

    async def close(self) -> None:
        self._snapshot_q.undeclare()
        for glove in self.gloves:
            glove.close()
        if self.board is not None:
            self.board.close()
