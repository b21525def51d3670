"""policy node: publish keypoint plans over a horizon at a fixed rate from the latest scene.

The method is a deployment parameter; the naive replay baseline needs no training, the learned
methods load a checkpoint written by `xm train`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.policy.naive import NaiveReplay
from services.world.teacher import generate_demo
from shared import msgs
from shared.demo import HAND_NAMES, KEYPOINTS_PER_HAND
from shared.runtime import Node, latest

POINT_NAMES = [f"{h}/{k}" for h in HAND_NAMES for k in range(KEYPOINTS_PER_HAND)]


class PolicyService:
    @dataclass
    class Params:
        method: str = "naive"
        rate_hz: float = 10.0
        horizon_s: float = 1.0
        plan_dt: float = 0.1
        task: str = "assembly"
        train_seeds: tuple[int, ...] = (9000, 9001, 9002)  # teacher demos the naive replay draws from

    def __init__(self, node: Node, params: Params) -> None:
        if params.method != "naive":
            raise ValueError(f"policy method {params.method!r}: this build serves 'naive' only")
        self.node = node
        self.p = params
        self.method = NaiveReplay()
        self.method.fit([generate_demo(params.task, s, index=i) for i, s in enumerate(params.train_seeds)])
        self.scene = None
        self.episode: tuple[int, float] | None = None  # (demo index, start time)
        self.pub = node.publisher("xm/policy/main/plan")
        node.subscribe("xm/recon/main/scene", self.on_scene, latest(1))
        node.subscribe("xm/world/sim/session", self.on_session, latest(1))

    def on_scene(self, msg) -> None:
        self.scene = msg

    def on_session(self, msg) -> None:
        if self.episode is None or self.episode[0] != msg.demo:
            self.episode = (msg.demo, msgs.stamp_seconds(msg.header.stamp))
            self.method.chosen = None

    async def run(self) -> None:
        steps = int(round(self.p.horizon_s / self.p.plan_dt)) + 1
        async for t in self.node.clock.ticks(self.p.rate_hz):
            if self.scene is None or self.episode is None:
                continue
            if self.method.chosen is None:
                objects = np.asarray(self.scene.object_keypoints, float).reshape(-1, 3)
                self.method.start(objects, np.asarray(self.scene.object_mask, bool))
            hands, _ = self.method.plan(t - self.episode[1], steps, self.p.plan_dt)
            points = hands.reshape(steps, -1, 3)
            if not np.isfinite(points).all():  # never let NaN reach trajopt
                self.node.stats.count("nan_plan")
                continue
            self.pub.put(msgs.make(
                "xm_msgs/msg/Plan", header=msgs.header(t, "world"), policy=self.method.name, dt=self.p.plan_dt,
                steps=steps, point_names=POINT_NAMES, positions=points.astype(np.float32).ravel(),
                mask=np.ones(points.shape[:2], np.uint8).ravel(), efforts=np.zeros(0, np.float32)))
