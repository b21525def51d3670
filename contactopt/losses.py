"""The physical consistency losses of the contact-based policy (thesis Eq. 2.8-2.13).

Each function returns residuals whose squares sum to its loss, so the Gauss-Newton optimizer can
use them directly. Pair i is (fingertip i, object): A is the fingertip sphere, B the object.
R is the ramp max(0, x). Residuals are scaled to dimensionless units (`Scales`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from contactopt import geometry as geo
from contactopt.sim import Step, World, object_sdf
from contactopt.tasks import Task

LOSSES = ("shape", "distance", "friction", "slippage", "intersection")


@dataclass(frozen=True)
class Scales:
    length: float = 0.01    # [m] a point 1 cm outside its shape costs 1
    force: float = 1.0      # [N]
    friction_force: float = 0.1  # [N] a force 0.1 N outside the friction cone costs 1
    speed: float = 0.1      # [m/s]
    weights: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0)  # per loss, in LOSSES' order


def shape_residual(s: Step, task: Task, world: World) -> torch.Tensor:
    """Eq. 2.9: both contact-point candidates inside their shapes (boundary planes)."""
    na, da = geo.circle_planes(world.tip_radius)
    in_a = geo.plane_violation(s.p_a - s.tips, na, da)
    r = geo.rot(s.theta)[:, None]  # object frame
    local_b = (r.transpose(-1, -2) @ (s.p_b - s.pos[:, None, :])[..., None])[..., 0]
    nb, db = geo.box_planes(task.size) if task.shape == "box" else geo.circle_planes(task.size)
    in_b = geo.plane_violation(local_b, nb, db)
    return torch.cat([in_a, in_b], -1)


def distance_residual(s: Step) -> torch.Tensor:
    """Eq. 2.10, force and distance complementary: F_C (x) (P_A - P_B) elementwise as printed, plus
    |F_C| |P_A - P_B|, without which a force perpendicular to the gap costs nothing (the policy
    finds that: tangential forces from fingertips centimetres away)."""
    gap = s.p_a - s.p_b
    return torch.cat([s.force * gap, (geo.norm(s.force) * geo.norm(gap))[..., None]], -1)


def contact_normal(s: Step, task: Task) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distance fingertip-object (B, 2) and the normal n_C (object outward, B, 2, 2)."""
    d_obj, n = object_sdf(s.tips, s.pos, s.theta, task)
    return d_obj, n


def friction_residual(s: Step, n: torch.Tensor, world: World) -> torch.Tensor:
    """Eq. 2.11: the force on the object inside the polygonal friction cone about -n_C (in the
    plane the cone has two boundary planes)."""
    t = torch.stack([-n[..., 1], n[..., 0]], -1)
    fn = -(s.force * n).sum(-1)
    ft = (s.force * t).sum(-1)
    mu = world.friction_mu
    return torch.stack([torch.relu(ft - mu * fn), torch.relu(-ft - mu * fn)], -1)


def slippage_residual(s: Step, n: torch.Tensor) -> torch.Tensor:
    """Eq. 2.12: F_C (x) tangential part of (V_CA - V_CB): no force while the contact slides."""
    point = 0.5 * (s.p_a + s.p_b)
    arm = point - s.pos[:, None, :]
    v_b = s.vel[:, None, :] + torch.stack([-arm[..., 1], arm[..., 0]], -1) * s.omega[:, None, None]
    v = s.tip_vel - v_b
    vt = v - n * (n * v).sum(-1, keepdim=True)
    return s.force * vt


def intersection_residual(d_obj: torch.Tensor, world: World) -> torch.Tensor:
    """Eq. 2.13: R(penetration depth) of fingertip and object."""
    return torch.relu(-(d_obj - world.tip_radius))


def step_residuals(s: Step, task: Task, world: World, scales: Scales) -> list[torch.Tensor]:
    """The five residuals of one step, each (B, ...) and dimensionless, in LOSSES' order."""
    d_obj, n = contact_normal(s, task)
    return [
        shape_residual(s, task, world) / scales.length,
        distance_residual(s) / (scales.force * scales.length),
        friction_residual(s, n, world) / scales.friction_force,
        slippage_residual(s, n) / (scales.force * scales.speed),
        intersection_residual(d_obj, world) / scales.length,
    ]
