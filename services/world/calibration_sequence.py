"""The simulated calibration sequence: board poses through the working volume, as a person waves it.

Pose 0 is the registration: the board lies face up on the table, which fixes the world frame
(``xm calibrate`` reads the same placement from the deployment's ``[calibration]`` table). The
others cover the volume above the table at heights up to 55 cm, tilted up to 60 degrees towards
any side and turned about their normal, so every camera sees the board from many angles, some
near the image border (partial views) and some nearly edge-on (which detection skips).
Poses are ``world_T_board`` (4x4) in the board frame of ``shared/charuco.py`` (z into the board).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from shared.charuco import BoardSpec

HIDDEN_Z = -1.0  # under the table: out of every camera's view
VOLUME_XY = 0.35  # board centres within +-35 cm of the table centre
VOLUME_Z = (0.03, 0.55)
MAX_TILT_DEG = 60.0


@dataclass(frozen=True)
class Registration:
    """Where the registration board lies: face up, centre at ``xy`` on the table, print rows along
    world x turned by ``yaw_deg`` about world z, its printed surface ``thickness_m`` above the table."""

    xy: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0
    thickness_m: float = 0.003

    @classmethod
    def from_dict(cls, data: dict) -> Registration:
        return cls((float(data.get("xy", (0, 0))[0]), float(data.get("xy", (0, 0))[1])),
                   float(data.get("yaw_deg", 0.0)), float(data.get("thickness_m", 0.003)))

    def to_dict(self) -> dict:
        return {"xy": list(self.xy), "yaw_deg": self.yaw_deg, "thickness_m": self.thickness_m}


FACE_UP = np.diag([1.0, -1.0, -1.0])  # board x along world x, board z (into the board) pointing down


def board_pose(board: BoardSpec, centre: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """world_T_board of a board whose centre is at ``centre`` with orientation ``rotation``."""
    w, h = board.size_m
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = np.asarray(centre, float) - rotation @ np.array([w / 2, h / 2, 0.0])
    return T


def registration_pose(board: BoardSpec, reg: Registration = Registration()) -> np.ndarray:
    R = Rotation.from_euler("z", reg.yaw_deg, degrees=True).as_matrix() @ FACE_UP
    return board_pose(board, np.array([reg.xy[0], reg.xy[1], reg.thickness_m]), R)


def sequence(board: BoardSpec, n: int = 120, seed: int = 0, reg: Registration = Registration()) -> list[np.ndarray]:
    """``n`` poses: the registration, then random ones through the working volume (deterministic in seed)."""
    if n < 1:
        raise ValueError(f"a calibration sequence needs at least 1 pose, got {n}")
    rng = np.random.default_rng(seed)
    poses = [registration_pose(board, reg)]
    for _ in range(n - 1):
        centre = np.array([*rng.uniform(-VOLUME_XY, VOLUME_XY, 2), rng.uniform(*VOLUME_Z)])
        azimuth = rng.uniform(0, 2 * np.pi)
        tilt = np.radians(MAX_TILT_DEG) * np.sqrt(rng.uniform())  # more poses near the larger tilts
        tilt_axis = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
        R = (Rotation.from_rotvec(tilt * tilt_axis) * Rotation.from_euler("z", rng.uniform(-np.pi, np.pi))
             ).as_matrix() @ FACE_UP
        poses.append(board_pose(board, centre, R))
    return poses


def mocap(world_T_board: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position, quaternion w x y z) of the board's mocap body."""
    q = Rotation.from_matrix(world_T_board[:3, :3]).as_quat()  # x y z w
    return world_T_board[:3, 3].copy(), np.array([q[3], q[0], q[1], q[2]])
