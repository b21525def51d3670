"""foxglove node: the cell live in the Foxglove app (docs/foxglove.md).

Forwards the keys of its ``keys`` parameter to the Foxglove SDK's WebSocket server
(ws://127.0.0.1:8765 by default) as ROS 2 CDR with our .msg definitions, every message as it
arrives on Zenoh's thread, and draws the scene's hands and objects as scene
entities and the robot's links as frame transforms. A key no service declares is counted
(``unregistered_key``) and not forwarded; ``@`` keys (health, commands) never are."""

from __future__ import annotations

import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from services.foxglove.driver import FoxgloveServer
from services.foxglove.entities import check_patterns, robot_frames, scene_entities
from shared import keys, msgs
from shared.config import DEFAULT_ROBOT
from shared.keys import is_internal
from shared.kinematics import URDFError, load_robot
from shared.runtime import Node
from shared.runtime.zsession import EndpointError

DEFAULT_KEYS = ["xm/recon/main/scene", "xm/robot/*/state", "xm/glove/*/tactile", "xm/policy/main/plan",
                "xm/world/sim/session", "xm/camhub/*/image", "xm/camhub/*/info"]


class FoxgloveService:
    @dataclass
    class Params:
        host: str = "127.0.0.1"  # loopback: the cell's data stays on this computer unless the deployment says so
        port: int = 8765  # Foxglove's default WebSocket port
        keys: list[str] = field(default_factory=lambda: list(DEFAULT_KEYS))  # key expressions forwarded
        robot: str = DEFAULT_ROBOT  # the robot model whose links are drawn
        name: str = "crossmodal"  # server name shown in the app

    def __init__(self, node: Node, params: Params) -> None:
        self.node = node
        self.p = params
        try:
            check_patterns(list(params.keys))
        except ValueError as exc:
            raise EndpointError(str(exc)) from None
        self.robot = None
        try:
            self.robot = load_robot(params.robot)
        except (FileNotFoundError, URDFError) as exc:  # hands and objects still drawn; health says why
            node.log.warning("no robot model, robot frames not drawn: %s", exc)
        try:
            self.server = FoxgloveServer(params.host, params.port, params.name)
        except Exception as exc:  # the SDK raises its own error type for a taken or invalid address
            raise EndpointError(f"foxglove: cannot listen on ws://{params.host}:{params.port} ({exc}); "
                                f"set [services.foxglove.<instance>] port to a free one") from None
        self.forwarded: Counter[str] = Counter()  # per key; handlers run on several Zenoh threads
        self._lock = threading.Lock()
        for pattern in params.keys:
            node.subscribe(pattern, self._forward, msgtype="raw", inline=True)  # no queue: the server keeps
            # a backlog per client and drops for a slow one
        node.input("scene", self._scene)
        node.input("state", self._state)
        node.health_extra = self.health
        node.set_status("ok", f"ws://{params.host}:{self.server.port}")

    def _forward(self, payload: bytes, key: str) -> None:
        if is_internal(key):
            return
        msgtype = keys.msgtype_of(key)
        if msgtype is None:
            self.node.stats.count("unregistered_key", key)
            return
        self.server.forward(key, msgtype, bytes(payload), time.time_ns())
        with self._lock:
            self.forwarded[key] += 1

    def _scene(self, msg: Any) -> None:
        if not self.server.wants_scene():
            return
        try:
            entities = scene_entities(msg)
        except ValueError as exc:  # lengths the validator let through but the hands do not fit
            self.node.stats.count("bad_scene")
            self.node.log.warning("scene not drawn: %s", exc)
            return
        self.server.draw(entities, msgs.stamp_seconds(msg.header.stamp), time.time_ns())

    def _state(self, msg: Any) -> None:
        if self.robot is None or not self.server.wants_frames():
            return
        frames = robot_frames(self.robot, list(msg.name), msg.position)
        self.server.transforms(frames, msgs.stamp_seconds(msg.header.stamp), time.time_ns())

    def health(self) -> dict:
        with self._lock:
            forwarded = dict(self.forwarded)
        return {"url": f"ws://{self.p.host}:{self.server.port}", "forwarded": forwarded,
                "robot_frames": self.robot is not None}

    async def close(self) -> None:
        self.server.stop()
