"""The 3-D differentiable simulator of tasks 3-8: a URDF hand (or arm and hand) moved kinematically
by the policy's joint velocity commands, and a free rigid object (cube) or an object on a vertical
revolute joint (cylinder, task 8), driven by gravity and the contact forces the policy predicts
(thesis Eq. 2.2-2.4), semi-implicit Euler.

Shape pairs: each fingertip sphere with the object and, for a free object, the table with the
object at each of the object's four bottom corners. The policy predicts every pair's two
contact-point candidates and force, the table's included, so nothing in the dynamics is
computed from the geometry: the consistency losses
(`losses3d`) make the predictions physical. The object is a uniform 0.1 kg cube (isotropic
inertia, so no gyroscopic term) or cylinder turning about Z only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import torch

from contactopt.handmodel import MODELS
from contactopt.kinematics import Chain, load_chain
from contactopt.policy import FORCE_SCALE, POS_SCALE, QDOT_SCALE, mlp
from contactopt.tasks3d import Task3D

F64 = torch.float64
MASS = 0.1
GRAVITY = 9.81
PRISMATIC_SCALE = 0.1  # prismatic commands: 0.2 m/s per unit (QDOT_SCALE 2 rad/s per unit)
# the hand's world pose (wrist mount) and joint positions at the start: fingertips 12 mm from the
# object's faces at 3.5 cm height
MOUNT = (-0.052, -0.008, 0.133)
Q0 = {"WRJ2": 0.076, "WRJ1": 0.054, "THJ5": 1.495, "LFJ5": 0.035, "RFJ4": 0.065, "MFJ4": 0.004,
      "FFJ4": -0.25, "FFJ3": 1.194, "FFJ2": 0.308, "MFJ3": 1.244, "MFJ2": 0.325, "RFJ3": 1.222,
      "RFJ2": 0.317, "LFJ4": 0.005, "LFJ3": 1.173, "LFJ2": 0.279, "THJ4": 0.302, "THJ3": 0.543,
      "THJ2": -0.12, "THJ1": 0.116}
# the table-object shape pairs: one per bottom corner of the cube (in units of its half extents).
# One pair's single response point could sit on the vertical axis the object turns about, where
# nothing slips: the cube would spin on the table with no torsional friction
BOTTOM = torch.tensor([[-1.0, -1.0, -1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [1.0, 1.0, -1.0]], dtype=F64)
# (object position (B, 3), rotation (B, 3, 3), joint positions (B, n)) -> (dof commands, P_A, P_B, F_C)
PolicyFn3 = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], tuple]


@dataclass
class Scene:
    chain: Chain
    base: torch.Tensor      # 4x4 world pose of the robot's root
    q0: torch.Tensor        # (n_joints,)
    cmd_scale: torch.Tensor  # (n_dof,) units of a command

    def n_pairs(self, task: Task3D) -> int:
        return len(self.chain.sphere_names) + (0 if task.fixed else len(BOTTOM))

    def n_in(self) -> int:
        return 9 + self.chain.n_joints

    def n_out(self, task: Task3D) -> int:
        return self.chain.n_dof + 9 * self.n_pairs(task)


@lru_cache
def scene(robot: str) -> Scene:
    chain = load_chain(MODELS / robot)
    base = torch.eye(4, dtype=F64)
    base[:3, 3] = torch.tensor(MOUNT, dtype=F64)
    dof0 = torch.tensor([Q0.get(n, 0.0) for n in chain.dof_names], dtype=F64)
    prismatic_dof = (chain.coupling.T @ chain.prismatic.to(F64)) > 0
    scale = torch.where(prismatic_dof, PRISMATIC_SCALE, 1.0) * QDOT_SCALE
    return Scene(chain, base, chain.coupling @ dof0, scale)


def object_start(task: Task3D, xy: torch.Tensor) -> torch.Tensor:
    """(B, 3) initial object centers: resting on the table at the sampled X, Y."""
    return torch.cat([xy, torch.full((xy.shape[0], 1), task.half[2], dtype=xy.dtype)], -1)


def features(task: Task3D, sc: Scene, pos: torch.Tensor, rot: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Policy input: object position (from its nominal start, in 5 cm), the first two columns of
    its rotation, joint positions (prismatic ones in 5 cm)."""
    rel = (pos - torch.tensor((0.0, 0.0, task.half[2]), dtype=pos.dtype)) / POS_SCALE
    qs = torch.where(sc.chain.prismatic, q / POS_SCALE, q)
    return torch.cat([rel, rot[..., :2].reshape(-1, 6), qs], -1)


def policy_fn(params: tuple[torch.Tensor, ...], task: Task3D, sc: Scene) -> PolicyFn3:
    """The network with explicit parameters as the simulator's policy."""
    n_dof, n_pairs = sc.chain.n_dof, sc.n_pairs(task)

    def pol(pos: torch.Tensor, rot: torch.Tensor, q: torch.Tensor) -> tuple:
        y = mlp(params, features(task, sc, pos, rot, q))
        c = y[:, n_dof:].reshape(-1, n_pairs, 9)
        return y[:, :n_dof], c[..., 0:3], c[..., 3:6], c[..., 6:9]
    return pol


def rodrigues(phi: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) rotation by the rotation vectors phi (B, 3); smooth at zero."""
    angle = torch.sqrt((phi * phi).sum(-1) + 1e-18)
    k = phi / angle[:, None]
    z = torch.zeros_like(angle)
    kx = torch.stack([torch.stack([z, -k[:, 2], k[:, 1]], -1), torch.stack([k[:, 2], z, -k[:, 0]], -1),
                      torch.stack([-k[:, 1], k[:, 0], z], -1)], -2)
    s, c = torch.sin(angle)[:, None, None], torch.cos(angle)[:, None, None]
    return torch.eye(3, dtype=phi.dtype) + s * kx + (1 - c) * (kx @ kx)


def inertia(task: Task3D) -> float:
    """The cube's (isotropic) moment of inertia, or the cylinder's about its axis."""
    if task.shape == "box":
        return MASS * (2 * task.half[0]) ** 2 / 6.0
    return MASS * task.half[0] ** 2 / 2.0


@dataclass
class Step3D:
    """What the consistency losses read, every step stacked and flattened to (B * T, ...)."""
    anchor_a: torch.Tensor  # (N, P, 3) fingertip centers; table pairs: the table below a bottom corner
    vel_a: torch.Tensor     # (N, P, 3) their velocities (zero for the table)
    pos: torch.Tensor       # (N, 3) object center
    rot: torch.Tensor       # (N, 3, 3)
    vel: torch.Tensor       # (N, 3) object velocity after the step
    omega: torch.Tensor     # (N, 3)
    p_a: torch.Tensor       # (N, P, 3) predicted contact point on the finger / table
    p_b: torch.Tensor       # (N, P, 3) on the object
    force: torch.Tensor     # (N, P, 3) force on the object


@dataclass
class Rollout3D:
    pos: torch.Tensor       # (B, T+1, 3)
    rot: torch.Tensor       # (B, T+1, 3, 3)
    omega: torch.Tensor     # (B, T, 3)
    hand_force: torch.Tensor   # (B, T, 3) the fingertips' net force on the object
    hand_torque: torch.Tensor  # (B, T, 3) their torque about the object's center
    tips: torch.Tensor      # (B, T+1, S, 3) fingertip centers
    steps: Step3D


def rollout3d(policy: PolicyFn3, task: Task3D, xy0: torch.Tensor) -> Rollout3D:
    """One batch of episodes from object positions xy0 (B, 2) under the predicted contacts."""
    sc = scene(task.robot)
    b, dt, n_tips = xy0.shape[0], task.dt, len(sc.chain.sphere_names)
    q = sc.q0.expand(b, -1)
    pos = object_start(task, xy0)
    rot = torch.eye(3, dtype=F64).expand(b, 3, 3)
    vel, omega = torch.zeros(b, 3, dtype=F64), torch.zeros(b, 3, dtype=F64)
    gravity = torch.tensor((0.0, 0.0, -GRAVITY), dtype=F64)
    inv_i = 1.0 / inertia(task)
    tips = sc.chain.sphere_centers(q, sc.base)
    poss, rots, omegas, hand_f, hand_t, tipss, record = [pos], [rot], [], [], [], [tips], []
    for _ in range(task.steps):
        cmd, off_a, off_b, force = policy(pos, rot, q)
        q_next = q + dt * (cmd * sc.cmd_scale) @ sc.chain.coupling.T
        tips_next = sc.chain.sphere_centers(q_next, sc.base)
        tip_vel = (tips_next - tips) / dt
        anchor, vel_a = tips, tip_vel
        if not task.fixed:  # the table pairs' anchors: the table below the object's bottom corners
            corners = pos[:, None] + (BOTTOM * torch.tensor(task.half, dtype=F64)) @ rot.transpose(-1, -2)
            below = corners * torch.tensor((1.0, 1.0, 0.0), dtype=F64)
            anchor = torch.cat([tips, below], 1)
            vel_a = torch.cat([tip_vel, torch.zeros_like(below)], 1)
        p_a = anchor + POS_SCALE * off_a
        p_b = pos[:, None] + POS_SCALE * off_b
        force = FORCE_SCALE * force
        arm = 0.5 * (p_a + p_b) - pos[:, None]  # Eq. 2.3: forces act at the midpoint
        torque = torch.linalg.cross(arm, force)
        hand_f.append(force[:, :n_tips].sum(1))
        hand_t.append(torque[:, :n_tips].sum(1))
        if task.fixed:  # only the turn about the joint's Z axis
            omega = omega + dt * inv_i * torque.sum(1) * torch.tensor((0.0, 0.0, 1.0), dtype=F64)
        else:
            vel = vel + dt * (force.sum(1) / MASS + gravity)
            omega = omega + dt * inv_i * torque.sum(1)
        record.append((anchor, vel_a, pos, rot, vel, omega, p_a, p_b, force))
        pos = pos + dt * vel
        rot = rodrigues(dt * omega) @ rot
        q, tips = q_next, tips_next
        poss.append(pos)
        rots.append(rot)
        omegas.append(omega)
        tipss.append(tips)
    cols = [torch.stack(c, 1) for c in zip(*record, strict=True)]
    steps = Step3D(*[c.reshape(-1, *c.shape[2:]) for c in cols])
    return Rollout3D(torch.stack(poss, 1), torch.stack(rots, 1), torch.stack(omegas, 1),
                     torch.stack(hand_f, 1), torch.stack(hand_t, 1), torch.stack(tipss, 1), steps)
