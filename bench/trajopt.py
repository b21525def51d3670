"""P3: receding-horizon trajectory optimization on the workcell (10 joints, 1 s horizon, 20 knots,
arm separation planes), our Gauss-Newton SQP (OSQP) against the plain casadi.Opti + IPOPT
formulation of the same problem, both warm-started, in the same run. Writes .bench/trajopt.json.
Target: p95 <= 10 ms on one core and >= 3x faster than the plain formulation."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import casadi as ca
import numpy as np

from services.trajopt.optimizer import TrajectoryOptimizer, TrajoptConfig
from shared.kinematics import load_robot

STEPS = 60
DT = 0.05


def goals_at(opt: TrajectoryOptimizer, t: float, q0: np.ndarray, K: int) -> np.ndarray:
    base = opt.points(q0)
    times = t + DT * np.arange(K)
    wobble = np.stack([0.05 * np.sin(times), 0.04 * np.cos(0.7 * times), -0.03 + 0.02 * np.sin(1.3 * times)], -1)
    return base[None] + wobble[:, None, :]


def plain_opti(model, cfg: TrajoptConfig, opt: TrajectoryOptimizer):
    """The same cost and constraints written directly with casadi.Opti, solved by IPOPT."""
    n, K, F = len(model.joint_names), cfg.knots, cfg.fixed_knots
    o = ca.Opti()
    Q = o.variable(K - F, n)
    fixed = o.parameter(F, n)
    goals = o.parameter(K * len(opt.frames), 3)
    sep = o.parameter(opt.separation.n_params)
    rows = [fixed[k, :] for k in range(F)] + [Q[k, :] for k in range(K - F)]
    cost = 0
    for k in range(F, K):
        q = rows[k].T
        p = opt._points(q)
        for i in range(len(opt.frames)):
            cost += ca.sumsqr(p[3 * i:3 * i + 3] - goals[k * len(opt.frames) + i, :].T)
        o.subject_to(p[2::3] >= cfg.table_z + cfg.sphere_radius)
        o.subject_to(opt.separation.constraint(q, sep) >= 0)
        o.subject_to(o.bounded(model.lower, q, model.upper))
    for k in range(F, K):
        o.subject_to(o.bounded(-model.max_velocity * DT, (rows[k] - rows[k - 1]).T, model.max_velocity * DT))
    for k in range(F, K - 1):
        acc = (rows[k + 1] - 2 * rows[k] + rows[k - 1]).T / DT ** 2
        o.subject_to(o.bounded(-cfg.acceleration_limit, acc, cfg.acceleration_limit))
        cost += cfg.accel_weight * ca.sumsqr(acc * DT)
    o.minimize(cost)
    o.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "warm_start_init_point": "yes"})
    return o, Q, fixed, goals, sep


def main() -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    model = load_robot("workcell")
    cfg = TrajoptConfig()
    opt = TrajectoryOptimizer(model, cfg)
    K, F, n = cfg.knots, cfg.fixed_knots, len(model.joint_names)
    q0 = np.zeros(n)
    q0[[2, 8]] = 0.25
    current = np.repeat(q0[None], K, 0)
    mask = np.ones((K, len(opt.frames)), bool)
    ours, errors = [], []
    for step in range(STEPS):
        goals = goals_at(opt, step * DT, q0, K)
        r = opt.solve(current, goals, mask, DT)
        if step >= 5:
            ours.append(r.solve_time_s)
            errors.append(np.linalg.norm(opt.points(r.q[-1]) - goals[-1], axis=1).max())
        current = np.concatenate([r.q[1:], r.q[-1:]])
    o, Q, fixed, goals_p, sep = plain_opti(model, cfg, opt)
    current = np.repeat(q0[None], K, 0)
    plain, plain_errors = [], []
    for step in range(STEPS):
        goals = goals_at(opt, step * DT, q0, K)
        o.set_value(fixed, current[:F])
        o.set_value(goals_p, goals.reshape(-1, 3))
        o.set_value(sep, opt.separation.params(current[F - 1]))
        o.set_initial(Q, current[F:])
        t0 = time.perf_counter()
        sol = o.solve()
        dt = time.perf_counter() - t0
        q = np.vstack([current[:F], np.asarray(sol.value(Q)).reshape(K - F, n)])
        if step >= 5:
            plain.append(dt)
            plain_errors.append(np.linalg.norm(opt.points(q[-1]) - goals[-1], axis=1).max())
        current = np.concatenate([q[1:], q[-1:]])
    res = {
        "problem": {"joints": n, "knots": K, "fixed_knots": F, "horizon_s": K * DT, "points": len(opt.frames),
                    "separation_pairs": opt.separation.n_rows, "solves": len(ours)},
        "ours_p50_ms": float(np.percentile(ours, 50) * 1e3), "ours_p95_ms": float(np.percentile(ours, 95) * 1e3),
        "plain_ipopt_p50_ms": float(np.percentile(plain, 50) * 1e3),
        "plain_ipopt_p95_ms": float(np.percentile(plain, 95) * 1e3),
        "ours_max_tracking_error_mm": float(np.max(errors) * 1e3),
        "plain_max_tracking_error_mm": float(np.max(plain_errors) * 1e3),
    }
    res["speedup_p50"] = res["plain_ipopt_p50_ms"] / res["ours_p50_ms"]
    res["speedup_p95"] = res["plain_ipopt_p95_ms"] / res["ours_p95_ms"]
    res["targets"] = {"ours_p95_ms_max": 10.0, "speedup_min": 3.0}
    Path(".bench").mkdir(exist_ok=True)
    Path(".bench/trajopt.json").write_text(json.dumps(res, indent=2))
    print(f"{'':>14}{'p50 ms':>9}{'p95 ms':>9}{'max err mm':>12}")
    print(f"{'ours (GN-SQP)':>14}{res['ours_p50_ms']:>9.2f}{res['ours_p95_ms']:>9.2f}"
          f"{res['ours_max_tracking_error_mm']:>12.3f}")
    print(f"{'Opti+IPOPT':>14}{res['plain_ipopt_p50_ms']:>9.2f}{res['plain_ipopt_p95_ms']:>9.2f}"
          f"{res['plain_max_tracking_error_mm']:>12.3f}")
    print(f"speedup: p50 {res['speedup_p50']:.1f}x, p95 {res['speedup_p95']:.1f}x (target >= 3x, p95 <= 10 ms)")


if __name__ == "__main__":
    main()
