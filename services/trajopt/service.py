"""trajopt node: receding-horizon control (thesis 7.4) from the latest plan and robot state to a
JointTrajectory, at a fixed rate. The maths is in optimizer.py; this file only moves messages."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from services.trajopt.hand_prior import DEFAULT_PRIOR, load_prior
from services.trajopt.mapping import goals_for_horizon, plan_arrays
from services.trajopt.optimizer import TrajectoryOptimizer, TrajoptConfig
from shared import msgs
from shared.kinematics import load_robot
from shared.robots.registry import DEFAULT_ROBOT, describe
from shared.runtime import Node


class TrajoptService:
    @dataclass
    class Params:
        robot: str = DEFAULT_ROBOT
        rate_hz: float = 10.0
        knots: int = 20
        horizon_s: float = 1.0
        fixed_knots: int = 2
        max_iterations: int = 2  # as deployed: the next cycle continues from this one (warm start)
        # 7.22 hand-pose regulariser, for robots whose description maps finger joints: the finger flexion
        # table of demonstrations in `prior` (services/trajopt/hand_prior.py).
        pose_weight: float = 1e-6
        prior: str = str(DEFAULT_PRIOR)

    _prepared: ClassVar[dict[str, tuple]] = {}  # a standby spare's optimizer, by its params

    @classmethod
    def prepare(cls, params: Params) -> None:
        """A standby spare builds its optimizer before it takes over (most of trajopt's start)."""
        cls._prepared[repr(params)] = cls._build(params)

    @staticmethod
    def _build(params: Params) -> tuple:
        model = load_robot(params.robot)
        desc = describe(params.robot)
        mean, std = {}, {}
        if desc.finger_flexion and params.pose_weight > 0:
            mean, std = load_prior(desc.finger_flexion, desc.finger_hand, params.prior)
        opt = TrajectoryOptimizer(model, TrajoptConfig(
            knots=params.knots, fixed_knots=params.fixed_knots, max_iterations=params.max_iterations,
            pose_mean=mean, pose_std=std, pose_weight=params.pose_weight if mean else 0.0))
        return model, mean, opt

    def __init__(self, node: Node, params: Params) -> None:
        self.node = node
        self.p = params
        built = self._prepared.pop(repr(params), None) or self._build(params)
        self.model, mean, self.opt = built
        if mean:
            node.log.info("hand-pose prior (7.22) over %d joints from %s, weight %g", len(mean), params.prior,
                          params.pose_weight)
        self.pose_prior = bool(mean)
        self.dt = params.horizon_s / params.knots
        self.plan = None
        self.state: np.ndarray | None = None
        self.current: np.ndarray | None = None  # the trajectory being executed, (knots, n)
        self.t_current = 0.0  # time of its first knot
        self.last_result = None
        self.last_rejection: dict | None = None  # the latest rejected solve, kept after later successes
        self.last_plan_rejection: str | None = None
        self.pub = node.output("trajectory")
        node.input("plan", self.on_plan)
        node.input("state", self.on_state)  # the robot's state: robot/<params.robot>/state by default
        node.health_extra = self._health

    def on_plan(self, msg) -> None:
        try:
            self.plan = plan_arrays(msg)
        except ValueError as exc:
            self.node.stats.count("bad_plan")
            self.last_plan_rejection = str(exc)
            self.node.reject("xm/policy/main/plan", "bad_value", str(exc))
            self.node.set_status("degraded", f"plan rejected: {exc}")

    def on_state(self, msg) -> None:
        order = {n: i for i, n in enumerate(msg.name)}
        try:
            self.state = np.array([msg.position[order[j]] for j in self.model.joint_names])
        except KeyError as exc:
            self.node.stats.count("state_missing_joint")
            self.node.set_status("degraded", f"robot state lacks joint {exc}")

    def _health(self) -> dict:
        r = self.last_result
        out = {"robot": self.p.robot, "pose_prior": self.pose_prior, "last_rejection": self.last_rejection,
               "last_plan_rejection": self.last_plan_rejection}
        if r is None:
            return out
        return out | {"solve_time_ms": round(r.solve_time_s * 1e3, 3), "iterations": r.iterations,
                      "max_violation": r.max_violation, "last_status": r.status, "reason": r.reason}

    async def run(self) -> None:
        async for t in self.node.clock.ticks(self.p.rate_hz):
            await self.tick(t)

    async def tick(self, t: float) -> None:
        """One control cycle at time t: solve from the latest plan and state, publish the trajectory
        being executed (the new one, or the last safe one when the solve was rejected)."""
        if self.state is None:
            return
        if self.current is None:
            self.current = np.repeat(self.state[None], self.p.knots, axis=0)
        if self.plan is None:  # no plan yet: hold (every goal masked)
            points = len(self.opt.point_names)
            goals, mask = np.zeros((self.p.knots, points, 3)), np.zeros((self.p.knots, points), bool)
        else:
            goals, mask = goals_for_horizon(self.plan, self.opt.point_names, t, self.dt, self.p.knots)
        # Shift the executing trajectory by the elapsed knots: its first knots stay fixed (continuity).
        shift = max(0, min(self.p.knots - 1, round((t - self.t_current) / self.dt))) if self.t_current else 0
        if shift:
            self.current = np.concatenate([self.current[shift:], np.repeat(self.current[-1:], shift, 0)])
        self.t_current = t
        result = await asyncio.to_thread(self.opt.solve, self.current, goals, mask, self.dt)
        self.last_result = result
        if result.ok:
            self.current = result.q
            self.node.set_status("ok")
        else:  # result.q is the executing trajectory: keep it (e.g. a failed QP is not a solution)
            self.node.stats.count("solve_rejected")
            self.last_rejection = {"t": t, "status": result.status, "reason": result.reason}
            self.node.set_status("degraded", f"kept last safe trajectory: {result.reason}")
        self.pub.put(self._trajectory_msg(t, self.current))

    def _trajectory_msg(self, t: float, q: np.ndarray):
        points = []
        for k in range(q.shape[0]):
            vel = (q[min(k + 1, len(q) - 1)] - q[max(k - 1, 0)]) / (self.dt * (2 if 0 < k < len(q) - 1 else 1))
            d = msgs.make("builtin_interfaces/msg/Duration", sec=int(k * self.dt),
                          nanosec=int(round((k * self.dt % 1) * 1e9)) % 1_000_000_000)
            points.append(msgs.make("trajectory_msgs/msg/JointTrajectoryPoint", positions=q[k].astype(float),
                                    velocities=vel.astype(float), accelerations=np.zeros(0), effort=np.zeros(0),
                                    time_from_start=d))
        return msgs.make("trajectory_msgs/msg/JointTrajectory", header=msgs.header(t, "world"),
                         joint_names=list(self.model.joint_names), points=points)
