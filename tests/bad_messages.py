"""A well-formed message of every registered type, and each kind of bad one built from it
(shared/runtime/validate.py's reasons): for the validation unit tests and the live flood test."""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import numpy as np

from shared import msgs
from shared.demo import HAND_NAMES, TACTILE_REGIONS
from shared.runtime import validate

JOINTS = ["a", "b", "c"]


def good(msgtype: str, t: float) -> Any:
    """A valid message of ``msgtype`` stamped ``t``."""
    h = msgs.header(t, "world")
    hands, objects = list(HAND_NAMES), ["box/0", "box/1"]
    f32 = np.float32
    if msgtype == "rosgraph_msgs/msg/Clock":
        return msgs.make(msgtype, clock=msgs.stamp(t))
    if msgtype == "xm_msgs/msg/GroundTruth":
        return msgs.make(msgtype, header=h, hand_names=hands, hand_keypoints=np.zeros(len(hands) * 63, f32),
                         hand_visible=np.ones(len(hands) * 21, np.uint8), object_names=objects,
                         object_keypoints=np.zeros(6, f32), object_visible=np.ones(2, np.uint8),
                         body_names=["box"], body_poses=np.zeros(7, f32), contact_forces=np.zeros(4, f32))
    if msgtype == "xm_msgs/msg/Session":
        return msgs.make(msgtype, header=h, task="assembly", demo=0, phase="approach", tactile_hand="left",
                         seed_layout="{}")
    if msgtype == "xm_msgs/msg/Scene":
        regions = len(hands) * len(TACTILE_REGIONS)
        return msgs.make(msgtype, header=h, hand_names=hands, hand_keypoints=np.zeros(len(hands) * 63, f32),
                         hand_mask=np.ones(len(hands) * 21, np.uint8), object_names=objects,
                         object_keypoints=np.zeros(6, f32), object_mask=np.ones(2, np.uint8),
                         tactile_regions=list(TACTILE_REGIONS), tactile=np.zeros(regions, f32),
                         tactile_mask=np.ones(regions, np.uint8))
    if msgtype == "xm_msgs/msg/TactileMesh":
        return msgs.make(msgtype, header=h, hand_names=["left"], vertex_count=3, vertices=np.zeros(9, f32),
                         faces=np.array([0, 1, 2], np.uint32), pressure=np.zeros(3, f32), sensed=np.ones(3, np.uint8))
    if msgtype == "xm_msgs/msg/Plan":
        return msgs.make(msgtype, header=h, policy="test", dt=0.1, steps=2, point_names=["left/8"],
                         positions=np.zeros(6, f32), mask=np.ones(2, np.uint8), efforts=np.zeros(0, f32))
    if msgtype == "trajectory_msgs/msg/JointTrajectory":
        points = [msgs.make("trajectory_msgs/msg/JointTrajectoryPoint", positions=np.zeros(3), velocities=np.zeros(3),
                            accelerations=np.zeros(0), effort=np.zeros(0),
                            time_from_start=msgs.make("builtin_interfaces/msg/Duration", sec=k, nanosec=0))
                  for k in range(2)]
        return msgs.make(msgtype, header=h, joint_names=list(JOINTS), points=points)
    if msgtype == "sensor_msgs/msg/JointState":
        return msgs.make(msgtype, header=h, name=list(JOINTS), position=np.zeros(3), velocity=np.zeros(3),
                         effort=np.zeros(3))
    if msgtype == "xm_msgs/msg/Tactile":
        return msgs.make(msgtype, header=h, hand="left", rows=16, cols=16, pressure=np.zeros(256, f32),
                         mask=np.ones(256, np.uint8), sequence=1)
    if msgtype == "sensor_msgs/msg/CompressedImage":
        return msgs.make(msgtype, header=h, format="jpeg", data=np.arange(16, dtype=np.uint8))
    if msgtype == "sensor_msgs/msg/CameraInfo":
        return msgs.make(msgtype, header=h, height=2, width=2, distortion_model="plumb_bob", d=np.zeros(5),
                         k=np.eye(3).ravel(), r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0,
                         roi=msgs.make("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0,
                                       width=0, do_rectify=False))
    raise KeyError(f"no sample for {msgtype}")


def _mutated(msg: Any, change: Callable[[Any], None]) -> Any:
    out = copy.deepcopy(msg)
    change(out)
    return out


def _set_nan(msg: Any) -> bool:
    """Puts a NaN into the first float array or float field found (depth first); False if none."""
    for name in msg.__dataclass_fields__:
        value = getattr(msg, name)
        if isinstance(value, np.ndarray) and value.dtype.kind == "f" and value.size:
            value[value.size // 2] = np.nan
            return True
        if isinstance(value, float) and name != "dt":
            setattr(msg, name, float("nan"))
            return True
        if isinstance(value, list) and value and hasattr(value[0], "__dataclass_fields__"):
            if _set_nan(value[0]):
                return True
    return False


def _shorten(msg: Any) -> bool:
    """Drops one value of the first array a length rule checks; False if the type has no rule."""
    rule = validate.LENGTH_RULES.get(msg.__msgtype__)
    if rule is None or msg.__msgtype__ in ("sensor_msgs/msg/CameraInfo", "sensor_msgs/msg/CompressedImage"):
        return False
    target = msg.points[0] if msg.__msgtype__ == "trajectory_msgs/msg/JointTrajectory" else msg
    for name in ("pressure", "real", "accel", "positions", "hand_keypoints", "position"):
        value = getattr(target, name, None)
        if isinstance(value, np.ndarray) and value.size:
            setattr(target, name, value[:-1])
            return True
    return False


def bad_payloads(msgtype: str, now: float) -> dict[str, bytes]:
    """Reason -> a payload that must be rejected for it, for every reason that applies to the type."""
    base = good(msgtype, now)
    out = {"malformed": b"\x00\x01\x00\x00\xff",  # too short for any type
           "oversized": b"\x00\x01\x00\x00" + bytes(validate.max_payload(msgtype))}
    nan = copy.deepcopy(base)
    if _set_nan(nan):
        out["non_finite"] = msgs.serialize(nan, msgtype)
    short = copy.deepcopy(base)
    if _shorten(short):
        out["bad_length"] = msgs.serialize(short, msgtype)
    if msgtype == "rosgraph_msgs/msg/Clock":
        out["bad_value"] = msgs.serialize(_mutated(base, lambda m: setattr(m.clock, "nanosec", 2_000_000_000)),
                                          msgtype)
    if msgtype == "xm_msgs/msg/Plan":
        out["bad_value"] = msgs.serialize(_mutated(base, lambda m: setattr(m, "dt", 0.0)), msgtype)
    if hasattr(base, "header"):
        out["stale_stamp"] = msgs.serialize(_mutated(base, lambda m: setattr(
            m.header, "stamp", msgs.stamp(now - 10 * validate.STALE_S))), msgtype)
        out["future_stamp"] = msgs.serialize(_mutated(base, lambda m: setattr(
            m.header, "stamp", msgs.stamp(now + 10 * validate.FUTURE_S + 60))), msgtype)
    return out
