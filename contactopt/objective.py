"""The objective of Eq. 2.7 as one residual vector: task residuals plus the consistency residuals
of every step, so that loss = |r|^2 is the batch mean of L_T + sum_t L_P,t (time-averaged)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from contactopt.losses import LOSSES, Scales, step_residuals
from contactopt.policy import Policy, apply
from contactopt.sim import Rollout, World, rollout
from contactopt.tasks import Task, task_residual


@dataclass(frozen=True)
class Objective:
    task: Task
    model: str = "predicted"
    world: World = World()
    scales: Scales = Scales()


def residual_parts(ro: Rollout, obj: Objective) -> list[torch.Tensor]:
    """[task (B,), one (B, n) per consistency loss (predicted model only)], unweighted squares
    sum to the per-sample losses."""
    parts = [task_residual(ro.theta0, ro.theta[:, -1], obj.task)]
    if ro.steps is None:
        return parts
    b, t = ro.theta.shape[0], ro.theta.shape[1] - 1
    for res, w in zip(step_residuals(ro.steps, obj.task, obj.world, obj.scales), obj.scales.weights, strict=True):
        parts.append((w / t) ** 0.5 * res.reshape(b, -1))
    return parts


def flat_params(policy: Policy) -> tuple[torch.Tensor, Callable[[torch.Tensor], dict[str, torch.Tensor]]]:
    """The policy's parameters as one vector and the map back to a parameter dict."""
    names = [n for n, _ in policy.named_parameters()]
    shapes = [p.shape for _, p in policy.named_parameters()]
    sizes = [p.numel() for _, p in policy.named_parameters()]
    flat = torch.cat([p.detach().reshape(-1) for _, p in policy.named_parameters()])

    def unflatten(w: torch.Tensor) -> dict[str, torch.Tensor]:
        return {n: c.reshape(s) for n, s, c in zip(names, shapes, torch.split(w, sizes), strict=True)}
    return flat, unflatten


def residual_fn(policy: Policy, obj: Objective, positions: torch.Tensor) -> Callable[[torch.Tensor], torch.Tensor]:
    """w -> r(w) on one batch of initial positions, scaled so |r|^2 is the batch mean loss."""
    _, unflatten = flat_params(policy)
    scale = positions.shape[0] ** -0.5

    def fn(w: torch.Tensor) -> torch.Tensor:
        params = tuple(unflatten(w).values())

        def pol(pos: torch.Tensor, theta: torch.Tensor, q: torch.Tensor) -> tuple:
            return apply(params, pos, theta, q, policy.contacts)
        ro = rollout(pol, obj.task, positions, obj.model, obj.world)
        return scale * torch.cat([p.reshape(p.shape[0], -1) for p in residual_parts(ro, obj)], 1).reshape(-1)
    return fn


def loss_breakdown(policy: Policy, obj: Objective, positions: torch.Tensor) -> dict[str, float]:
    """Batch-mean task loss and each consistency loss, for logs and reports."""
    with torch.no_grad():
        ro = rollout(policy, obj.task, positions, obj.model, obj.world)
        parts = residual_parts(ro, obj)
    out = {"task": float((parts[0] ** 2).mean())}
    for name, p in zip(LOSSES, parts[1:], strict=True):
        out[name] = float((p ** 2).sum(1).mean())
    return out
