"""The key registry: every key of the workcell, its message type, publisher and nominal rate.

Contract tests, the recorder and the integration test read this table; a service publishing a
key that is not here is a bug. Rates are those of the simulated deployment (deploy/sim.toml).
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass

GLOVES = ("left", "right")
CAMERAS = tuple(f"cam{i}" for i in range(7))


@dataclass(frozen=True)
class KeySpec:
    key: str  # a concrete key; the registry enumerates instances
    msgtype: str
    service: str
    rate_hz: float  # nominal rate in the simulated deployment
    description: str
    on_change: bool = False  # also published whenever the value changes: rate_hz is a minimum


def _specs() -> list[KeySpec]:
    specs = [
        KeySpec("xm/clock", "rosgraph_msgs/msg/Clock", "world", 100.0, "simulated time"),
        KeySpec("xm/world/sim/truth", "xm_msgs/msg/GroundTruth", "world", 50.0,
                "simulator truth, for evaluation only"),
        KeySpec("xm/world/sim/session", "xm_msgs/msg/Session", "world", 1.0, "task/demo/phase label",
                on_change=True),
        KeySpec("xm/recon/main/scene", "xm_msgs/msg/Scene", "recon", 5.0, "reconstructed keypoints"),
        KeySpec("xm/policy/main/plan", "xm_msgs/msg/Plan", "policy", 5.0,
                "keypoint plan over a horizon, one per reconstructed scene"),
        KeySpec("xm/trajopt/main/trajectory", "trajectory_msgs/msg/JointTrajectory", "trajopt", 10.0,
                "joint trajectory for the robot"),
        KeySpec("xm/robot/workcell/state", "sensor_msgs/msg/JointState", "robot", 100.0,
                "measured joint positions, velocities, motor currents as effort"),
    ]
    for hand in GLOVES:
        specs.append(KeySpec(f"xm/glove/{hand}/tactile", "xm_msgs/msg/Tactile", "glove", 100.0,
                             "calibrated 16x16 pressure"))
    for cam in CAMERAS:
        specs.append(KeySpec(f"xm/camhub/{cam}/image", "sensor_msgs/msg/CompressedImage", "camhub", 5.0,
                             "JPEG frame, triggered together"))
        specs.append(KeySpec(f"xm/camhub/{cam}/info", "sensor_msgs/msg/CameraInfo", "camhub", 5.0,
                             "intrinsics of the frame"))
    return specs


REGISTRY: tuple[KeySpec, ...] = tuple(_specs())
BY_KEY: dict[str, KeySpec] = {spec.key: spec for spec in REGISTRY}

# Optional keys: published only when enabled, typed here so the recorder can store them.
OPTIONAL: dict[str, str] = {
    "xm/glove/*/raw": "xm_msgs/msg/TactileRaw",
    "xm/glove/*/imu": "xm_msgs/msg/Imu",
    # The robot service publishes on its own instance's key, named after the robot model
    # (robot_state_key): xm/robot/workcell/state above, xm/robot/hand_arm/state in deploy/hand_arm.toml.
    "xm/robot/*/state": "sensor_msgs/msg/JointState",
}


def robot_state_key(robot: str) -> str:
    """Where the measured state of robot model ``robot`` is published: the robot service's instance
    carries the model's name (``[services.robot.<robot>]``), so trajopt and panel find it from theirs."""
    return service_key("robot", robot, "state")


def msgtype_of(key: str) -> str | None:
    """Message type of a concrete key, or None when the key is not registered."""
    spec = BY_KEY.get(key)
    if spec is not None:
        return spec.msgtype
    for pattern, msgtype in OPTIONAL.items():
        if fnmatch.fnmatchcase(key, pattern):
            return msgtype
    return None


def matching(pattern: str) -> list[KeySpec]:
    """Registered keys matching a Zenoh-style pattern (`*` one chunk, `**` any chunks)."""
    return [spec for spec in REGISTRY if key_matches(pattern, spec.key)]


def key_matches(pattern: str, key: str) -> bool:
    p, k = pattern.split("/"), key.split("/")

    def match(i: int, j: int) -> bool:
        if i == len(p):
            return j == len(k)
        if p[i] == "**":
            return any(match(i + 1, jj) for jj in range(j, len(k) + 1))
        if j == len(k):
            return False
        return fnmatch.fnmatchcase(k[j], p[i]) and match(i + 1, j + 1)

    return match(0, 0)


def service_key(service: str, instance: str, topic: str) -> str:
    return f"xm/{service}/{instance}/{topic}"
