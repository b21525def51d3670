"""From a Plan message to the optimizer's goal array (pure)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared import msgs
from shared.robots.make_workcell_urdf import GRIP_AXIS


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


def with_grip_axis(plan: PlanArrays, hand: str = "left") -> PlanArrays:
    """Adds the derived point ``<hand>/grip_axis`` (pinch midpoint + GRIP_AXIS along thumb -> index,
    level), the goal of the workcell's ``left_grip_axis``:
    it gives the gripper's yaw a lever; the fingertips alone are 5 mm apart. Unchanged when the plan
    lacks either fingertip or already has the point."""
    names = plan.names
    thumb, index, axis = f"{hand}/4", f"{hand}/8", f"{hand}/grip_axis"
    if axis in names or thumb not in names or index not in names:
        return plan
    a, b = plan.positions[:, names.index(thumb)], plan.positions[:, names.index(index)]
    d = (b - a) * [1.0, 1.0, 0.0]
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    ok = plan.mask[:, names.index(thumb)] & plan.mask[:, names.index(index)] & (norm[:, 0] > 1e-4)
    point = 0.5 * (a + b) + GRIP_AXIS * d / np.maximum(norm, 1e-9)
    return PlanArrays(plan.stamp, plan.dt, names + [axis], np.concatenate([plan.positions, point[:, None]], axis=1),
                      np.concatenate([plan.mask, ok[:, None]], axis=1))


def goals_for_horizon(plan: PlanArrays, wanted: list[str], t0: float, dt: float, knots: int) -> tuple[np.ndarray,
                                                                                                     np.ndarray]:
    """Goals (knots, len(wanted), 3) at times t0 + k*dt, interpolated in the plan; mask False where
    the plan lacks a point, masks it, or the time lies outside the plan. Derived points (the
    gripper's grip axis) are added from the fingertips first."""
    plan = with_grip_axis(plan)
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
