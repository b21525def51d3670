"""The trajectory optimizer's settings and result (pure data; the optimizer is optimizer.py)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

TABLE = ((0.0, 0.0, -1.0), 0.0)  # N . p <= P - r  <=>  z >= r


class TrajoptInputError(ValueError):
    """The executing trajectory or the goals have the wrong shape."""


@dataclass
class TrajoptConfig:
    knots: int = 20
    fixed_knots: int = 2
    point_map: dict[str, str] | None = None  # plan point -> robot frame; None: the description's point_map
    point_weights: dict[str, float] = field(default_factory=dict)  # plan point -> weight (default 1)
    trust_region: float = 0.1  # rad or m per SQP iteration (7.18)
    max_iterations: int = 2  # per control cycle; the next cycle continues from this one (warm start)
    step_tolerance: float = 1e-4  # stop when no joint moves more than this in an iteration
    damping: float = 1e-3  # added to the Gauss-Newton Hessian
    model_tolerance: float = 1e-2  # or when the QP model predicted the new cost (relative to the decrease)
    accel_time: float = 0.1  # acceleration limit = velocity limit / accel_time (7.19)
    smooth_weight: float = 1e-3  # weight of squared accelerations * dt^2 (keeps H well conditioned)
    planes: list[tuple[tuple[float, float, float], float]] = field(default_factory=lambda: [TABLE])  # (7.20)
    sphere_radii: dict[str, float] | None = None  # keypoint frame -> sphere radius; None: 5 mm on every keypoint
    collision_pairs: list[tuple[str, str]] | None = None  # link pairs (7.21); None: the description's
    margin: float = 0.005  # minimum distance between shapes of a pair
    near: float = 0.02  # covering-sphere gap under which GJK/EPA computes the exact separation
    contact_slots: int = 4  # separating-plane rows per knot, given to the closest shape pairs
    pose_mean: dict[str, float] = field(default_factory=dict)  # 7.22: joint -> mean (services/trajopt/hand_prior)
    pose_std: dict[str, float] = field(default_factory=dict)
    pose_weight: float = 0.0
    qp_solver: str = "ipqp"
    qp_options: dict = field(default_factory=dict)
    violation_tolerance: float = 1e-3  # a result violating a constraint by more is rejected
    reach_padding: float = 0.02  # goals this far outside the sampled workspace box are unreachable
    # Plans keep this far inside the URDF joint limits: wider than the robot service's soft-limit margin
    # (services/robot/safety.py), so the robot never clamps a plan and tracking overshoot stays inside.
    limit_margin_m: float = 0.001  # prismatic joints
    limit_margin_rad: float = 0.005  # revolute joints


@dataclass
class TrajoptResult:
    q: np.ndarray  # (knots, n joints), full joint order (mimic joints included)
    status: str  # solved | max_iterations | unreachable | infeasible | qp_failed | bad_input
    ok: bool
    solve_time_s: float
    iterations: int
    max_violation: float
    reason: str = ""
    cost: float = float("nan")
