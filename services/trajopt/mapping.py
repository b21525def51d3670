"""From a Plan message to the optimizer's goal array (pure)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared import msgs
from shared.robots.registry import derived_points


@dataclass
class PlanArrays:
    stamp: float
    dt: float
    names: list[str]
    positions: np.ndarray  # (steps, points, 3)
    mask: np.ndarray  # (steps, points) bool


def plan_arrays(msg) -> PlanArrays:
    names = list(msg.point_names)
    steps, points = int(msg.steps), len(names)
    pos = np.asarray(msg.positions, float)
    if pos.size != steps * points * 3 or not msg.dt > 0:
        raise ValueError(f"plan of {steps} steps x {points} points has {pos.size} position values, dt {msg.dt}")
    if len(msg.mask) not in (0, steps * points):
        raise ValueError(f"plan of {steps} steps x {points} points has {len(msg.mask)} mask values")
    mask = np.asarray(msg.mask, bool).reshape(steps, points) if len(msg.mask) else np.ones((steps, points), bool)
    bad = mask & ~np.isfinite(pos.reshape(steps, points, 3)).all(axis=-1)
    if bad.any():  # a goal the plan asks for that is no number: the plan is broken, not partly usable
        raise ValueError(f"plan has {int(bad.sum())} non-finite keypoints of {int(mask.sum())} unmasked")
    return PlanArrays(msgs.stamp_seconds(msg.header.stamp), float(msg.dt), names, pos.reshape(steps, points, 3), mask)


def with_derived_point(plan: PlanArrays, name: str) -> PlanArrays:
    """Adds the derived plan point ``name`` (shared/robots: the midpoint of its two source points
    moved its offset along a -> b, level). The workcell's ``left/grip_axis`` is the goal of its
    ``left_grip_axis`` frame: it gives the gripper's yaw a lever; the fingertips alone are 5 mm
    apart. Unchanged when the plan lacks either source point or already has the point."""
    spec = derived_points().get(name)
    if spec is None:
        raise ValueError(f"no robot description derives the plan point {name!r} (known: {sorted(derived_points())})")
    names = plan.names
    if name in names or spec.a not in names or spec.b not in names:
        return plan
    a, b = plan.positions[:, names.index(spec.a)], plan.positions[:, names.index(spec.b)]
    d = (b - a) * [1.0, 1.0, 0.0]
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    ok = plan.mask[:, names.index(spec.a)] & plan.mask[:, names.index(spec.b)] & (norm[:, 0] > 1e-4)
    point = 0.5 * (a + b) + spec.offset * d / np.maximum(norm, 1e-9)
    return PlanArrays(plan.stamp, plan.dt, names + [name], np.concatenate([plan.positions, point[:, None]], axis=1),
                      np.concatenate([plan.mask, ok[:, None]], axis=1))


def with_grip_axis(plan: PlanArrays, hand: str = "left") -> PlanArrays:
    """``with_derived_point`` for ``<hand>/grip_axis``."""
    return with_derived_point(plan, f"{hand}/grip_axis")


def goals_for_horizon(plan: PlanArrays, wanted: list[str], t0: float, dt: float, knots: int) -> tuple[np.ndarray,
                                                                                                     np.ndarray]:
    """Goals (knots, len(wanted), 3) at times t0 + k*dt, interpolated in the plan; mask False where
    the plan lacks a point, masks it, or the time lies outside the plan. Wanted derived points (the
    gripper's grip axis) are added from their source points first."""
    derived = derived_points()
    for name in wanted:
        if name in derived:
            plan = with_derived_point(plan, name)
    goals = np.zeros((knots, len(wanted), 3))
    mask = np.zeros((knots, len(wanted)), bool)
    index = {n: i for i, n in enumerate(plan.names)}
    times = plan.stamp + plan.dt * np.arange(len(plan.positions))
    for j, name in enumerate(wanted):
        i = index.get(name)
        if i is None:
            continue
        for k in range(knots):
            t = t0 + k * dt
            if t < times[0] - plan.dt or t > times[-1]:
                continue
            s = np.clip((t - times[0]) / plan.dt, 0, len(times) - 1)
            a = int(np.floor(s))
            b = min(a + 1, len(times) - 1)
            w = s - a
            if plan.mask[a, i] and plan.mask[b, i]:
                goals[k, j] = (1 - w) * plan.positions[a, i] + w * plan.positions[b, i]
                mask[k, j] = np.isfinite(goals[k, j]).all()
    return goals, mask
