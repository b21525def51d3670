"""What the bridge draws, as plain data (no Foxglove types): hands and objects of a Scene as
scene entities, the robot's links as frame transforms, and which keys are forwarded."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import zenoh
from scipy.spatial.transform import Rotation

from shared.demo import KEYPOINTS_PER_HAND
from shared.kinematics import RobotModel

WORLD = "world"
FINGERS = ((1, 2, 3, 4), (5, 6, 7, 8), (9, 10, 11, 12), (13, 14, 15, 16), (17, 18, 19, 20))
# bones of the MANO/OpenPose hand: wrist to each finger's base, then along each finger
BONES = tuple((0, f[0]) for f in FINGERS) + tuple((a, b) for f in FINGERS for a, b in zip(f, f[1:], strict=False))
HAND_COLORS = {"left": (0.2, 0.6, 1.0, 1.0), "right": (1.0, 0.45, 0.2, 1.0)}
OBJECT_COLOR = (0.3, 0.85, 0.35, 1.0)
KEYPOINT_M = 0.008  # sphere diameter of a keypoint


@dataclass
class Entity:
    """One scene entity: spheres at points and a line list (pairs of points), one colour each."""

    id: str
    color: tuple[float, float, float, float]
    points: np.ndarray  # (N, 3) sphere centres
    lines: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (2M, 3): segment ends in pairs
    label: str = ""


@dataclass
class Transform:
    parent: str
    child: str
    translation: np.ndarray  # (3,)
    rotation: np.ndarray  # (4,) quaternion x y z w


def scene_entities(scene: object) -> list[Entity]:
    """A hand entity per hand (observed keypoints and the bones between observed pairs) and an
    entity per object (its observed keypoints); the entity ids stay the same from scene to scene,
    so each update replaces the last."""
    out = []
    names = list(scene.hand_names)
    kp = np.asarray(scene.hand_keypoints, float).reshape(len(names), KEYPOINTS_PER_HAND, 3)
    mask = np.asarray(scene.hand_mask, bool).reshape(len(names), KEYPOINTS_PER_HAND)
    for h, name in enumerate(names):
        seen = mask[h]
        bones = [(a, b) for a, b in BONES if seen[a] and seen[b]]
        lines = kp[h][np.array(bones).ravel()] if bones else np.zeros((0, 3))
        out.append(Entity(f"hand/{name}", HAND_COLORS.get(name, (0.8, 0.8, 0.8, 1.0)), kp[h][seen], lines,
                          f"{name} hand"))
    pts = np.asarray(scene.object_keypoints, float).reshape(-1, 3)
    omask = np.asarray(scene.object_mask, bool)
    groups: dict[str, list[int]] = {}
    for i, n in enumerate(scene.object_names):
        groups.setdefault(n.split("/", 1)[0], []).append(i)
    for obj, idx in groups.items():
        sel = [i for i in idx if i < len(pts) and i < len(omask) and omask[i]]
        out.append(Entity(f"object/{obj}", OBJECT_COLOR, pts[sel], label=obj))
    return out


def robot_frames(model: RobotModel, names: list[str], positions: np.ndarray) -> list[Transform]:
    """World -> link transform of every link of ``model`` at the measured joint positions (joints
    matched by name; a joint the state does not name stays at 0)."""
    q = np.zeros(len(model.joint_names))
    index = {n: i for i, n in enumerate(names)}
    for i, n in enumerate(model.joint_names):
        if n in index:
            q[i] = positions[index[n]]
    out = []
    for link, T in model.fk(q).items():
        if link == WORLD:
            continue
        out.append(Transform(WORLD, link, T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3]).as_quat()))
    return out


def check_patterns(patterns: list[str]) -> list[str]:
    """Forwarded key expressions: valid Zenoh expressions under xm/; ValueError says which is not."""
    for p in patterns:
        try:
            zenoh.KeyExpr(p)
        except zenoh.ZError as exc:
            raise ValueError(f"foxglove: keys entry {p!r} is not a Zenoh key expression ({exc})") from None
        if not p.startswith("xm/"):
            raise ValueError(f"foxglove: keys entry {p!r}: workcell keys start with xm/")
    return patterns

