"""robot node: follow the latest JointTrajectory through the control board at the command rate,
enforcing joint, velocity and effort limits whatever arrives, and publish the measured state."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass

import numpy as np

from services.robot.driver import BoardDriver
from services.robot.safety import CommandRejectedError, Limits, check_finite, limit_step, pneumatic_joints
from services.robot.tracking import TrajectoryFollower
from shared import msgs
from shared.keys import robot_state_key
from shared.kinematics import load_robot
from shared.protocols.robot_board import Mode
from shared.robots.registry import DEFAULT_ROBOT, describe
from shared.runtime import Node


def command_modes(joint_names: list[str], finger_mode: str = "position") -> np.ndarray:
    """The board mode per joint: POSITION, or PNEUMATIC for joints with a muscle pair when
    ``finger_mode`` is "pneumatic". Raises ValueError for an unknown finger mode or a robot without
    pneumatic joints (the board would brake them: services/robot/safety.py)."""
    modes = np.full(len(joint_names), Mode.POSITION, np.uint8)
    if finger_mode == "position":
        return modes
    if finger_mode != "pneumatic":
        raise ValueError(f"robot: finger_mode must be 'position' or 'pneumatic', got {finger_mode!r}")
    drive = pneumatic_joints(tuple(joint_names))
    if not drive.any():
        raise ValueError("robot: finger_mode = 'pneumatic', but no joint of this robot has a pneumatic drive "
                         "(only the hand-arm's finger joints do)")
    modes[drive] = Mode.PNEUMATIC
    return modes


class RobotService:
    @dataclass
    class Params:
        port: str = ""
        baudrate: int = 3_000_000
        robot: str = DEFAULT_ROBOT
        command_rate_hz: float = 250.0
        state_rate_hz: float = 100.0
        # "pneumatic": joints with a muscle pair (the hand-arm's fingers) follow the trajectory in the
        # board's PNEUMATIC mode (two-stage pressure PID, thesis 7.3.2) instead of POSITION.
        finger_mode: str = "position"

    def __init__(self, node: Node, params: Params) -> None:
        self.node = node
        self.p = params
        model = load_robot(params.robot)
        self.joint_names = model.joint_names
        self.limits = Limits.from_model(model)
        self.modes = command_modes(self.joint_names, params.finger_mode)
        self.follower = TrajectoryFollower(self.joint_names)
        self.driver = BoardDriver(params.port, params.baudrate, describe(params.robot).board_order, node.log)
        if node.instance != params.robot:  # trajopt and panel look for xm/robot/<robot model>/state
            node.log.warning("robot instance %r runs model %r: its state goes to %s, not %s", node.instance,
                             params.robot, node.key("state"), robot_state_key(params.robot))
        self.state_pub = node.output("state")
        self.rejections: dict[str, int] = {}
        self.target: np.ndarray | None = None
        node.input("trajectory", self.on_trajectory)
        node.queryable("hold", self.cmd_hold)
        node.clock.on_jump(lambda _old, _new: self.cmd_hold({}))  # a trajectory of the old timeline: hold
        node.health_extra = lambda: {"link": self.driver.link.stats(), "decoder": dict(self.driver.decoder.stats),
                                     "rejections": self.rejections, "watchdog": self.driver.watchdog_state}

    def _reject(self, reason: str) -> None:
        self.rejections[reason] = self.rejections.get(reason, 0) + 1
        self.node.stats.count("command_rejected")
        self.node.logs.warning(f"rejected:{reason}", "trajectory rejected", reason=reason)

    def on_trajectory(self, msg) -> None:
        reason = self.follower.load(msg, self.node.clock.now())
        if reason:
            self._reject(reason)

    def cmd_hold(self, _req: dict) -> dict:
        self.follower = TrajectoryFollower(self.joint_names)
        return {"ok": True}

    async def run(self) -> None:
        self.node.spawn(self.driver.run(), name="serial")
        self.node.spawn(self._publish_state(), name="state")
        period = 1.0 / self.p.command_rate_hz
        # Commands go out on wall time: the board's watchdog must be fed even if the sim clock stalls.
        while True:
            await asyncio.sleep(period)
            self._command_tick(period)

    def _command_tick(self, dt: float) -> None:
        fb = self.driver.feedback
        if fb is None:
            return  # no state, no commands: the board's watchdog keeps the robot braked
        if self.target is None:
            self.target = fb.position.copy()  # start by holding where the robot is
        sample = self.follower.sample(self.node.clock.now())
        goal, velocity = sample if sample is not None else (self.target, np.zeros(len(self.target)))
        try:
            check_finite(goal, "trajectory sample")
        except CommandRejectedError as exc:
            self._reject(str(exc))
            goal, velocity = self.target, np.zeros(len(self.target))
        self.target, reasons = limit_step(goal, self.target, self.limits, dt)
        for r in reasons:
            self.node.stats.count(f"clamped_{r}")
        velocity = np.clip(velocity, -self.limits.velocity, self.limits.velocity)
        self.driver.send(self.modes, self.target, velocity, np.zeros(len(self.target)))

    async def _publish_state(self) -> None:
        async for t in self.node.clock.ticks(self.p.state_rate_hz):
            fb = self.driver.feedback
            if fb is None:
                self.node.set_status("degraded", "no feedback from the control board")
                continue
            self.node.set_status("ok" if not fb.watchdog_expired else "degraded",
                                 "" if not fb.watchdog_expired else "board watchdog braking")
            self.state_pub.put(msgs.make(
                "sensor_msgs/msg/JointState", header=msgs.header(t, "world"), name=list(self.joint_names),
                position=fb.position.astype(float), velocity=fb.velocity.astype(float),
                effort=fb.current.astype(float)))

    async def close(self) -> None:
        self.driver.close()
