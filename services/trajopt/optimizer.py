"""The trajectory optimizer of thesis 7.4 as a Gauss-Newton SQP (pure; no I/O).

Decision variables: joint positions at knots t_f+1..t_h (the first t_f knots are fixed to the
executing trajectory). Cost (7.16): weighted squared distances between mapped robot points and
the plan's goals, plus a small acceleration penalty and, for hand-arm models, the hand-pose
regulariser (7.22). Constraints: joint limits (7.17), a trust region per iteration (7.18),
velocity and acceleration limits (7.19), workspace planes against collision spheres (7.20) and
separating planes between the two arms' convex shapes initialised by coal GJK/EPA (7.21).

Each SQP iteration is one call of a CasADi function (residual, Jacobian, linearised constraints,
all code-generated as SX) and one interior-point/active-set QP; warm starts come from shifting
the previous solution, so 1-3 iterations suffice at 10-100 Hz replanning.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from services.trajopt.collision import ArmSeparation
from shared.kinematics import RobotModel

# Plan keypoint -> robot frame for the workcell: the gripper executes the left hand's thumb and
# index tips, the single finger the right hand's index tip.
WORKCELL_MAP = {"left_tip_a": "left/4", "left_tip_b": "left/8", "right_tip": "right/8"}


@dataclass
class TrajoptConfig:
    knots: int = 20
    fixed_knots: int = 2
    point_map: dict[str, str] = field(default_factory=lambda: dict(WORKCELL_MAP))
    trust_region: float = 0.05  # rad or m per SQP iteration (7.18)
    max_iterations: int = 3
    accel_weight: float = 1e-4
    acceleration_limit: float = 5.0  # m/s^2 or rad/s^2 (7.19)
    table_z: float = 0.0
    sphere_radius: float = 0.002  # fingertip collision spheres against the table plane (7.20)
    arm_clearance: float = 0.02  # minimum distance between the two arms' shapes (7.21)
    pose_mean: dict[str, float] = field(default_factory=dict)  # 7.22 regulariser (hand-arm)
    pose_std: dict[str, float] = field(default_factory=dict)
    pose_weight: float = 0.0
    qp_solver: str = "osqp"
    tolerance: float = 1e-6


@dataclass
class TrajoptResult:
    q: np.ndarray
    ok: bool
    status: str
    reason: str
    solve_time_s: float
    iterations: int
    max_violation: float
    cost: float


class TrajectoryOptimizer:
    def __init__(self, model: RobotModel, config: TrajoptConfig | None = None) -> None:
        self.model = model
        self.cfg = cfg = config or TrajoptConfig()
        self.n = len(model.joint_names)
        self.frames = list(cfg.point_map)
        self.point_names = [cfg.point_map[f] for f in self.frames]
        self.lower, self.upper, self.vmax = model.lower, model.upper, model.max_velocity
        self.free = cfg.knots - cfg.fixed_knots
        self.separation = ArmSeparation.for_model(model, cfg.arm_clearance)
        self._build()
        self.last: np.ndarray | None = None

    # --- symbolic problem ---------------------------------------------------------------
    def _build(self) -> None:
        cfg, n, K, F = self.cfg, self.n, self.cfg.knots, self.cfg.fixed_knots
        P = len(self.frames)
        x = ca.SX.sym("x", self.free * n)  # free knots
        fixed = ca.SX.sym("fixed", F * n)
        goals = ca.SX.sym("goals", K * P * 3)
        weights = ca.SX.sym("w", K * P)
        dt = ca.SX.sym("dt")
        sep = ca.SX.sym("sep", self.separation.n_params)
        Q = ca.vertcat(fixed, x)
        q_at = [Q[k * n:(k + 1) * n] for k in range(K)]
        res, cons, clb, cub = [], [], [], []
        q_sym = ca.SX.sym("q", n)
        fk = self.model.fk_casadi(q_sym)
        points = ca.Function("points", [q_sym], [ca.vertcat(*[fk[f][1] for f in self.frames])])
        tips = ca.Function("tips", [q_sym], [ca.vertcat(*[fk[f][1][2] for f in self.frames])])
        for k in range(F, K):
            p = points(q_at[k])
            for i in range(P):
                j = (k * P + i)
                res.append(ca.sqrt(weights[j]) * (p[3 * i:3 * i + 3] - goals[3 * j:3 * j + 3]))
            if cfg.pose_weight > 0:
                for name, mu in cfg.pose_mean.items():
                    idx = self.model.joint_names.index(name)
                    res.append(np.sqrt(cfg.pose_weight) * (q_at[k][idx] - mu) / cfg.pose_std.get(name, 1.0))
            # 7.20: fingertip spheres stay above the table plane (normal -z): z >= table + r
            cons.append(tips(q_at[k]))
            clb += [cfg.table_z + cfg.sphere_radius] * P
            cub += [np.inf] * P
            cons.append(self.separation.constraint(q_at[k], sep))
            clb += [0.0] * self.separation.n_rows
            cub += [np.inf] * self.separation.n_rows
        for k in range(max(1, F), K):  # 7.19 velocities (from the last fixed knot on)
            cons.append((q_at[k] - q_at[k - 1]) / dt)
            clb += list(-self.vmax)
            cub += list(self.vmax)
        for k in range(max(1, F), K - 1):
            cons.append((q_at[k + 1] - 2 * q_at[k] + q_at[k - 1]) / dt ** 2)
            clb += [-cfg.acceleration_limit] * n
            cub += [cfg.acceleration_limit] * n
            res.append(np.sqrt(cfg.accel_weight) * (q_at[k + 1] - 2 * q_at[k] + q_at[k - 1]) / dt)
        r = ca.vertcat(*res)
        g = ca.vertcat(*cons)
        J = ca.jacobian(r, x)
        G = ca.jacobian(g, x)
        self._clb, self._cub = np.array(clb, float), np.array(cub, float)
        H = ca.mtimes(J.T, J)
        self._eval = ca.Function("sqp_terms", [x, fixed, goals, weights, dt, sep],
                                 [H, ca.mtimes(J.T, r), g, G, ca.sumsqr(r)])
        self._points = points
        self._H_sp = H.sparsity() + ca.Sparsity.diag(x.numel())
        self._qp = ca.conic("qp", cfg.qp_solver, {"h": self._H_sp, "a": G.sparsity()},
                            _qp_options(cfg.qp_solver))

    # --- solve ------------------------------------------------------------------------------
    def solve(self, current: np.ndarray, goals: np.ndarray, goal_mask: np.ndarray, dt: float) -> TrajoptResult:
        """current: (K,n) executing trajectory; goals: (K,P,3) in point_names order; goal_mask: (K,P)."""
        t0 = time.perf_counter()
        cfg, n, K, F = self.cfg, self.n, self.cfg.knots, self.cfg.fixed_knots
        current = np.asarray(current, float)
        if current.shape != (K, n) or not np.isfinite(current).all():
            return self._fail(current, "current trajectory has the wrong shape or non-finite values", t0)
        goals = np.asarray(goals, float)
        mask = np.asarray(goal_mask, bool)
        if goals.shape != (K, len(self.frames), 3):
            return self._fail(current, f"goals shape {goals.shape}, expected {(K, len(self.frames), 3)}", t0)
        bad = ~np.isfinite(goals).all(axis=-1)
        if (bad & mask).any():
            return self._fail(current, "plan goals contain NaN or infinite values", t0)
        goals = np.where(bad[..., None], 0.0, goals)
        weights = mask.astype(float).ravel()
        fixed = current[:F].ravel()
        x = np.clip(current[F:], self.lower, self.upper).ravel()
        sep = self.separation.params(current[F - 1] if F else current[0])
        lo = np.tile(self.lower, self.free)
        hi = np.tile(self.upper, self.free)
        iterations = 0
        while iterations < cfg.max_iterations:
            iterations += 1
            H, grad, g, G, cost = self._eval(x, fixed, goals.ravel(), weights, dt, sep)
            H = H + 1e-6 * ca.DM.eye(x.size)
            g = np.asarray(g).ravel()
            lbx = np.maximum(lo - x, -cfg.trust_region)
            ubx = np.minimum(hi - x, cfg.trust_region)
            sol = self._qp(h=H, g=grad, a=G, lba=self._clb - g, uba=self._cub - g, lbx=lbx, ubx=ubx,
                           x0=np.zeros(x.size))
            step = np.asarray(sol["x"]).ravel()
            if not np.isfinite(step).all():
                return self._fail(current, "QP returned non-finite step", t0)
            x = np.clip(x + step, lo, hi)
            if np.max(np.abs(step)) < cfg.tolerance:
                break
        _, _, g, _, cost = self._eval(x, fixed, goals.ravel(), weights, dt, sep)
        g = np.asarray(g).ravel()
        violation = float(np.max(np.concatenate([np.maximum(self._clb - g, 0), np.maximum(g - self._cub, 0), [0]])))
        q = np.concatenate([current[:F], x.reshape(self.free, n)])
        ok = violation < 1e-3
        reason = "" if ok else f"constraint violation {violation:.3g} after {iterations} iterations"
        if ok:
            self.last = q
        return TrajoptResult(q if ok else current, ok, "solved" if ok else "infeasible", reason,
                             time.perf_counter() - t0, iterations, violation, float(cost))

    def points(self, q: np.ndarray) -> np.ndarray:
        """Mapped robot points (P,3) for one joint vector."""
        return np.asarray(self._points(q)).reshape(-1, 3)

    def _fail(self, current: np.ndarray, reason: str, t0: float) -> TrajoptResult:
        return TrajoptResult(current, False, "rejected", reason, time.perf_counter() - t0, 0, np.inf, np.nan)


def _qp_options(solver: str) -> dict:
    if solver == "osqp":
        return {"osqp": {"verbose": False, "eps_abs": 1e-5, "eps_rel": 1e-5, "polish": False, "max_iter": 1000},
                "warm_start_primal": True, "error_on_fail": False}
    if solver == "qrqp":
        return {"print_iter": False, "print_header": False, "error_on_fail": False}
    return {"error_on_fail": False}
