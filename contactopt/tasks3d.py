"""Tasks 3-8 of thesis Table 2.1: the five-finger hand (on a 6-joint arm for lift and push) and a
cube or cylinder, in 3-D.

World: table top at z = 0, X forward (the direction the fingers point), Z up, the thumb on +Y
(the hand's left). The hand starts above the object, palm down, its fingertips 12 mm from the
object's +X face and the thumb's from its -X face. The object starts at the origin plus Gaussian
noise (sigma 5 mm) in X and Y. Episodes: 10 semi-implicit Euler steps of 50 ms (0.5 s; with
every contact force predicted, nothing in the dynamics is stiff).

Task losses (thesis 2.3): lift and push, the object's pose at termination against a goal pose
(position in cm, orientation as sin(angle) x axis in units of 0.2 rad); turn and flip, the
average angular velocity vector against the goal vector, relative to the goal's magnitude; the
fixed cylinder adds the forces and tilting torques the hand puts on the mounting joint.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

T_EPISODE = 10 * 0.05


@dataclass(frozen=True)
class Task3D:
    name: str
    robot: str                     # URDF file in contactopt/models
    shape: str                     # "box" or "cylinder" (upright, axis Z)
    half: tuple[float, float, float]  # half extents; a cylinder: (radius, radius, half height)
    goal: str                      # "pose" (displacement at termination) or "velocity" (average)
    target: tuple[float, float, float]  # goal displacement [m] or angular velocity [rad/s]
    fixed: bool = False            # object on a vertical revolute joint (task 8)
    joint_load_weight: float = 0.0
    steps: int = 10
    dt: float = 0.05
    position_sigma: float = 0.005
    success_tolerance: float = 0.2
    criterion: str = ""            # the success criterion in words, for the docs and the report

    @property
    def size(self) -> float:
        return self.half[0]


CUBE = (0.025, 0.025, 0.025)
CYLINDER = (0.025, 0.025, 0.025)
FLIP = math.pi / 2 / T_EPISODE  # a quarter turn in one episode
TASKS3D: dict[str, Task3D] = {t.name: t for t in (
    Task3D("lift", "arm_hand.urdf", "box", CUBE, "pose", (0.0, 0.0, 0.05),
           criterion="mean lift of the cube within 20 % of 5 cm, mean horizontal drift under 1 cm"),
    Task3D("push", "arm_hand.urdf", "box", CUBE, "pose", (0.05, 0.0, 0.0),
           criterion="mean push along X within 20 % of 5 cm, mean drift in Y and Z under 1 cm"),
    Task3D("hand_turn", "hand.urdf", "box", CUBE, "velocity", (0.0, 0.0, 1.0),
           criterion="mean turn velocity about Z within 20 % of 1 rad/s"),
    Task3D("flip_backwards", "hand.urdf", "box", CUBE, "velocity", (0.0, -FLIP, 0.0),
           criterion="mean rotation about -Y (top towards the wrist) within 20 % of a quarter turn"),
    Task3D("flip_left", "hand.urdf", "box", CUBE, "velocity", (-FLIP, 0.0, 0.0),
           criterion="mean rotation about -X (top towards the thumb) within 20 % of a quarter turn"),
    Task3D("fixed_cylinder", "hand.urdf", "cylinder", CYLINDER, "velocity", (0.0, 0.0, 1.0), fixed=True,
           joint_load_weight=1.0,
           criterion="mean turn velocity about Z within 20 % of 1 rad/s"),
)}

POSITION_UNIT = 0.01     # [m] pose residual units
ANGLE_UNIT = 0.2         # [rad]
LOAD_FORCE_UNIT = 1.0    # [N] joint-load residual units
LOAD_TORQUE_UNIT = 0.05  # [N m]


def vee_skew(r: torch.Tensor) -> torch.Tensor:
    """sin(angle) * axis of rotation matrices (..., 3, 3): zero at the identity, smooth."""
    return 0.5 * torch.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0],
                              r[..., 1, 0] - r[..., 0, 1]], -1)


def average_omega(omega: torch.Tensor) -> torch.Tensor:
    """(B, 3) average angular velocity over an episode's steps (B, T, 3)."""
    return omega.mean(1)


def task_residual3d(task: Task3D, pos: torch.Tensor, rot: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
    """(B, 6) or (B, 3) task residual from object positions (B, T+1, 3), rotations (B, T+1, 3, 3)
    and angular velocities (B, T, 3)."""
    target = torch.tensor(task.target, dtype=pos.dtype)
    if task.goal == "pose":
        dp = (pos[:, -1] - pos[:, 0] - target) / POSITION_UNIT
        return torch.cat([dp, vee_skew(rot[:, -1]) / ANGLE_UNIT], -1)
    return (average_omega(omega) - target) / target.norm()


def joint_load_residual(task: Task3D, forces: torch.Tensor, torques: torch.Tensor) -> torch.Tensor:
    """Task 8: the hand's net force (3) and tilting torque (X, Y) on the mounting joint at every
    step, (B, T * 5), time-averaged so the squares sum to the mean load loss."""
    b, t = forces.shape[:2]
    r = torch.cat([forces / LOAD_FORCE_UNIT, torques[..., :2] / LOAD_TORQUE_UNIT], -1)
    return (task.joint_load_weight / t) ** 0.5 * r.reshape(b, -1)


def task_metric(task: Task3D, pos: torch.Tensor, omega: torch.Tensor) -> dict[str, float]:
    """The quantity of the success criterion, averaged over the batch: "metric" (lift height,
    push distance, or the average angular velocity about the goal axis), "drift" (pose tasks:
    the displacement off the goal direction)."""
    target = torch.tensor(task.target, dtype=pos.dtype)
    axis = target / target.norm()
    if task.goal == "pose":
        d = pos[:, -1] - pos[:, 0]
        along = d @ axis
        drift = (d - along[:, None] * axis).norm(dim=-1)
        return {"metric": float(along.mean()), "drift": float(drift.mean()), "goal": float(target.norm())}
    return {"metric": float((average_omega(omega) @ axis).mean()), "drift": 0.0, "goal": float(target.norm())}


def success3d(task: Task3D, metric: dict[str, float]) -> bool:
    ok = abs(metric["metric"] - metric["goal"]) <= task.success_tolerance * metric["goal"]
    return ok and (task.goal != "pose" or metric["drift"] < 0.01)
