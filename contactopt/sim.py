"""A planar differentiable rigid-body simulator of two fingers and a free object on a table.

The fingers are two-link planar arms, velocity-controlled (the policy's joint velocity commands
move them kinematically, as position servos would); only their spherical fingertips touch the
object. The object is a free rigid body in SE(2) on the table, with smooth Coulomb table friction
applied implicitly. Semi-implicit Euler: velocities first, positions from the new velocities.

Contact forces come from one of three models:
- ``hard``: the baseline of thesis 2.4, Hooke normal force D_M max(0, -d) from the penetration
  depth, tangential force from the relative velocity projected into the friction cone;
- ``softplus``: Eq. 2.1, F = D_M C_S ln(1 + exp(-d / C_S)), friction smoothed;
- ``predicted``: the contact-based policy's forces applied at the midpoint of its two predicted
  contact points (Eq. 2.3-2.4), nothing computed from the geometry.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as nnf

from contactopt import geometry as geo
from contactopt.policy import FORCE_SCALE, POS_SCALE
from contactopt.tasks import Task

MODELS = ("hard", "softplus", "predicted")
# (object position, object angle, joint positions) -> (joint velocities, P_A, P_B, F_C)
PolicyFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], tuple]


@dataclass(frozen=True)
class World:
    mass: float = 0.1              # object [kg]
    table_mu: float = 0.3          # object-table friction coefficient
    table_eps_v: float = 0.01      # [m/s] smoothing of the table's Coulomb friction
    table_eps_w: float = 0.1       # [rad/s]
    gravity: float = 9.81
    tip_radius: float = 0.01       # fingertip sphere [m]
    links: tuple[float, float] = (0.07, 0.07)
    bases: tuple[tuple[float, float], ...] = ((-0.12, 0.0), (0.12, 0.0))
    base_angles: tuple[float, ...] = (0.0, math.pi)  # finger 1 reaches along +x, finger 2 along -x
    q0: tuple[float, ...] = (1.1, -2.2, 1.1, -2.2)  # bent fingers, tips 1.6 cm from the cube
    stiffness: float = 200.0       # D_M [N/m]
    smoothness: float = 0.005      # C_S [m]
    friction_mu: float = 0.8       # finger-object friction (also the predicted forces' cone)
    friction_damping: float = 50.0  # [N s/m] tangential force per relative velocity below the cone
    friction_eps: float = 0.01     # [m/s] smoothing of the softplus model's friction


def fingertips(q: torch.Tensor, world: World) -> torch.Tensor:
    """(B, 2, 2) fingertip centers of joint positions q (B, 4)."""
    l1, l2 = world.links
    qq = q.reshape(-1, 2, 2)
    a1 = torch.tensor(world.base_angles, dtype=q.dtype) + qq[..., 0]
    a2 = a1 + qq[..., 1]
    base = torch.tensor(world.bases, dtype=q.dtype)
    return base + l1 * torch.stack([torch.cos(a1), torch.sin(a1)], -1) + l2 * torch.stack(
        [torch.cos(a2), torch.sin(a2)], -1)


def object_sdf(p: torch.Tensor, pos: torch.Tensor, theta: torch.Tensor,
               task: Task) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distance of points p (B, K, 2) to the object and its outward normal there."""
    if task.shape == "box":
        return geo.sdf_box(p, pos[:, None, :], theta[:, None], task.size)
    if task.shape == "cylinder":
        return geo.sdf_circle(p, pos[:, None, :], task.size)
    raise ValueError(f"unknown shape {task.shape!r}; shapes: box, cylinder")


def inertia(task: Task, world: World) -> float:
    if task.shape == "box":
        return world.mass * (2 * task.size) ** 2 / 6.0
    return world.mass * task.size ** 2 / 2.0


def cross_w(w: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Planar w x r for angular velocities w (B,) and arms r (B, K, 2)."""
    return torch.stack([-r[..., 1], r[..., 0]], -1) * w[:, None, None]


def cross_z(r: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """z component of r x f, summed over the last-but-one axis."""
    return (r[..., 0] * f[..., 1] - r[..., 1] * f[..., 0]).sum(-1)


def simulated_forces(tips: torch.Tensor, tip_vel: torch.Tensor, pos: torch.Tensor, theta: torch.Tensor,
                     vel: torch.Tensor, omega: torch.Tensor, task: Task, world: World,
                     model: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Contact forces on the object (B, 2, 2), their points (B, 2, 2) and the distances (B, 2)."""
    d_obj, n = object_sdf(tips, pos, theta, task)
    d = d_obj - world.tip_radius
    point = tips - n * d_obj[..., None]
    if model == "hard":
        fn = world.stiffness * torch.relu(-d)
    elif model == "softplus":
        c = world.smoothness
        fn = world.stiffness * c * nnf.softplus(-d / c)
    else:
        raise ValueError(f"unknown contact model {model!r}; models: hard, softplus")
    v_rel = tip_vel - (vel[:, None, :] + cross_w(omega, point - pos[:, None, :]))
    vt = v_rel - n * (n * v_rel).sum(-1, keepdim=True)
    if model == "hard":  # viscous below the cone, projected onto it above
        ft = world.friction_damping * vt
        limit = world.friction_mu * fn
        mag = geo.norm(ft)
        ft = ft * torch.clamp(limit / mag, max=1.0)[..., None]
    else:
        ft = world.friction_mu * fn[..., None] * vt / torch.sqrt((vt * vt).sum(-1, keepdim=True)
                                                                 + world.friction_eps ** 2)
    return -n * fn[..., None] + ft, point, d


@dataclass
class Step:
    """What the consistency losses read (predicted model); leading axis: samples, or samples
    times steps once stacked."""
    tips: torch.Tensor       # (B, 2, 2) fingertip centers
    tip_vel: torch.Tensor    # (B, 2, 2)
    pos: torch.Tensor        # object position (B, 2)
    theta: torch.Tensor      # (B,)
    vel: torch.Tensor        # object velocity after the step (B, 2)
    omega: torch.Tensor      # (B,)
    p_a: torch.Tensor        # predicted contact point on the finger (B, 2, 2)
    p_b: torch.Tensor        # predicted contact point on the object
    force: torch.Tensor      # predicted force on the object


@dataclass
class Rollout:
    theta0: torch.Tensor
    theta: torch.Tensor      # (B, T+1)
    pos: torch.Tensor        # (B, T+1, 2)
    steps: Step | None       # the predicted model's steps, flattened to (B * T, ...)


def rollout(policy: PolicyFn, task: Task, obj_pos0: torch.Tensor, model: str,
            world: World = World()) -> Rollout:
    """Run one episode from the object positions obj_pos0 (B, 2) with the given contact model."""
    if model not in MODELS:
        raise ValueError(f"unknown contact model {model!r}; models: {', '.join(MODELS)}")
    b = obj_pos0.shape[0]
    dt = task.dt
    inv_i = 1.0 / inertia(task, world)
    q = torch.tensor(world.q0, dtype=torch.float64).expand(b, -1)
    pos, theta = obj_pos0, torch.zeros(b, dtype=torch.float64)
    vel, omega = torch.zeros(b, 2, dtype=torch.float64), torch.zeros(b, dtype=torch.float64)
    thetas, poss, record = [theta], [pos], []
    friction = world.table_mu * world.gravity
    # the table's friction torque, mu m g times the mean lever arm of a disk (2/3 of its radius)
    spin_friction = friction * world.mass * (2.0 / 3.0) * task.size * inv_i
    tips = fingertips(q, world)
    for _ in range(task.steps):
        qdot, off_a, off_b, force = policy(pos, theta, q)
        q_next = q + dt * qdot
        tips_next = fingertips(q_next, world)
        tip_vel = (tips_next - tips) / dt
        if model == "predicted":
            if force is None:
                raise ValueError("the predicted contact model needs a contact-based policy")
            p_a = tips + POS_SCALE * off_a          # candidate on the fingertip, relative to it
            p_b = pos[:, None, :] + POS_SCALE * off_b  # candidate on the object, relative to it
            force = FORCE_SCALE * force
            point = 0.5 * (p_a + p_b)  # Eq. 2.3: the response point
        else:
            force, point, _ = simulated_forces(tips, tip_vel, pos, theta, vel, omega, task, world, model)
        f_total = force.sum(1)
        torque = cross_z(point - pos[:, None, :], force)
        # semi-implicit Euler; the table's smooth Coulomb friction is taken implicitly (stable
        # at any step for any smoothing): v' = (v + dt a) / (1 + dt mu g / sqrt(|v|^2 + eps^2))
        vel = (vel + dt * f_total / world.mass) / (
            1 + dt * friction / torch.sqrt((vel * vel).sum(-1) + world.table_eps_v ** 2))[:, None]
        omega = (omega + dt * torque * inv_i) / (
            1 + dt * spin_friction / torch.sqrt(omega * omega + world.table_eps_w ** 2))
        if model == "predicted":
            record.append((tips, tip_vel, pos, theta, vel, omega, p_a, p_b, force))
        pos = pos + dt * vel
        theta = theta + dt * omega
        q, tips = q_next, tips_next
        thetas.append(theta)
        poss.append(pos)
    th = torch.stack(thetas, 1)
    steps = None
    if record:  # every step's quantities stacked and flattened to (B * T, ...) for the losses
        cols = [torch.stack(c, 1) for c in zip(*record, strict=True)]
        steps = Step(*[c.reshape(-1, *c.shape[2:]) for c in cols])
    return Rollout(th[:, 0], th, torch.stack(poss, 1), steps)
