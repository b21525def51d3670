"""The Foxglove SDK's WebSocket server: one channel per forwarded key (ROS 2 CDR bytes as they are
on the wire, the key's .msg definition as a ``ros2msg`` schema), a scene-update channel for hands
and objects and a frame-transforms channel for the robot's links.

Every bridge has its own SDK context, so two bridges in one process (tests) do not share channels."""

from __future__ import annotations

import foxglove
from foxglove.channels import FrameTransformsChannel, SceneUpdateChannel
from foxglove.messages import (
    Color,
    FrameTransform,
    FrameTransforms,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

from services.foxglove.entities import KEYPOINT_M, WORLD, Entity, Transform
from shared import msgs

SCENE_TOPIC = "/xm/scene"  # hands and objects as scene entities
FRAMES_TOPIC = "/tf"  # robot link frames: the topic Foxglove's 3D panel looks at first


class FoxgloveServer:
    """A running WebSocket server with lazily created channels."""

    def __init__(self, host: str, port: int, name: str) -> None:
        self.context = foxglove.Context()
        self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context)
        self.channels: dict[str, foxglove.Channel] = {}
        self.scene = SceneUpdateChannel(SCENE_TOPIC, context=self.context)
        self.frames = FrameTransformsChannel(FRAMES_TOPIC, context=self.context)

    @property
    def port(self) -> int:
        return self.server.port

    def forward(self, key: str, msgtype: str, payload: bytes, log_time_ns: int) -> None:
        """Log raw CDR bytes on the key's channel (advertised to clients when first used)."""
        ch = self.channels.get(key)
        if ch is None:
            schema = foxglove.Schema(name=msgtype, encoding="ros2msg", data=msgs.schema_text(msgtype).encode())
            ch = self.channels[key] = foxglove.Channel(key, schema=schema, message_encoding="cdr",
                                                       context=self.context)
        ch.log(payload, log_time=log_time_ns)

    def wants_scene(self) -> bool:
        """Whether a client subscribes to the scene entities (else they need not be built)."""
        return self.scene.has_sinks()

    def wants_frames(self) -> bool:
        return self.frames.has_sinks()

    def draw(self, entities: list[Entity], stamp_s: float, log_time_ns: int) -> None:
        ts = _timestamp(stamp_s)
        self.scene.log(SceneUpdate(entities=[_entity(e, ts) for e in entities]), log_time=log_time_ns)

    def transforms(self, frames: list[Transform], stamp_s: float, log_time_ns: int) -> None:
        ts = _timestamp(stamp_s)
        self.frames.log(FrameTransforms(transforms=[
            FrameTransform(timestamp=ts, parent_frame_id=f.parent, child_frame_id=f.child,
                           translation=Vector3(x=float(f.translation[0]), y=float(f.translation[1]),
                                               z=float(f.translation[2])),
                           rotation=Quaternion(x=float(f.rotation[0]), y=float(f.rotation[1]),
                                               z=float(f.rotation[2]), w=float(f.rotation[3])))
            for f in frames]), log_time=log_time_ns)

    def stop(self) -> None:
        self.server.stop()


def _timestamp(stamp_s: float) -> Timestamp:
    sec = int(stamp_s // 1)
    return Timestamp(sec, min(int(round((stamp_s - sec) * 1e9)), 999_999_999))


def _entity(e: Entity, ts: Timestamp) -> SceneEntity:
    color = Color(r=e.color[0], g=e.color[1], b=e.color[2], a=e.color[3])
    size = Vector3(x=KEYPOINT_M, y=KEYPOINT_M, z=KEYPOINT_M)
    spheres = [SpherePrimitive(pose=_pose(p), size=size, color=color) for p in e.points]
    lines = ([LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=0.002, color=color,
                            points=[Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in e.lines])]
             if len(e.lines) else [])
    texts = ([TextPrimitive(pose=_pose(e.points[0] + [0.0, 0.0, 0.03]), billboard=True, font_size=12.0,
                            scale_invariant=True, color=color, text=e.label)] if e.label and len(e.points) else [])
    return SceneEntity(timestamp=ts, frame_id=WORLD, id=e.id, spheres=spheres, lines=lines, texts=texts)


def _pose(p) -> Pose:
    return Pose(position=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
