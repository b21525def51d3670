"""Planar geometry of the primitives: signed distances, normals and boundary planes.

Shapes are seen from above: a box (cube) is a square, an upright cylinder and a sphere are
circles. Everything is batched torch and differentiable (square roots are smoothed at zero).
"""

from __future__ import annotations

import math

import torch

EPS = 1e-12


def rot(theta: torch.Tensor) -> torch.Tensor:
    """(..., 2, 2) rotation matrices of angles (...)."""
    c, s = torch.cos(theta), torch.sin(theta)
    return torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)


def norm(v: torch.Tensor) -> torch.Tensor:
    return torch.sqrt((v * v).sum(-1) + EPS)


def sdf_circle(p: torch.Tensor, center: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distance of points p (..., 2) to a circle and the outward normal at the closest point."""
    diff = p - center
    dist = norm(diff)
    return dist - radius, diff / dist[..., None]


def sdf_box(p: torch.Tensor, center: torch.Tensor, theta: torch.Tensor,
            half: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distance of points p (..., 2) to a square of half side `half` at (center, theta),
    and the outward normal (the distance's gradient) in world coordinates."""
    r = rot(theta)
    local = (r.transpose(-1, -2) @ (p - center)[..., None])[..., 0]
    q = local.abs() - half
    outside = q.clamp(min=0.0)
    d_out = norm(outside)
    d_in = torch.maximum(q[..., 0], q[..., 1]).clamp(max=0.0)
    is_out = (q > 0).any(-1)
    sign = torch.where(local >= 0, 1.0, -1.0).to(p.dtype)
    n_out = outside * sign / norm(outside)[..., None]
    x_axis = q[..., 0] >= q[..., 1]
    n_in = torch.stack([torch.where(x_axis, sign[..., 0], 0.0), torch.where(x_axis, 0.0, sign[..., 1])], -1)
    n_local = torch.where(is_out[..., None], n_out, n_in)
    d = torch.where(is_out, d_out, d_in)
    return d, (r @ n_local[..., None])[..., 0]


def circle_planes(radius: float, n: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """Boundary planes (N, d) of a regular n-gon circumscribing a circle: inside where N p + d <= 0."""
    a = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    normals = torch.stack([torch.cos(a), torch.sin(a)], -1)
    return normals, torch.full((n,), -radius, dtype=torch.float64)


def box_planes(half: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The four boundary planes of a square of half side `half` (in its own frame)."""
    normals = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]], dtype=torch.float64)
    return normals, torch.full((4,), -half, dtype=torch.float64)


def plane_violation(p: torch.Tensor, normals: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """R(N_l p + d_l) for every plane l: (..., L); zero when p is inside."""
    return torch.relu(p @ normals.T + offsets)
