"""The trajectory optimizer of thesis 7.4 (pure; no I/O): keypoint goals -> joint trajectory.

Decision variables are the independent joint positions at knots t_f..t_h-1 (the first t_f knots
are the executing trajectory, held for continuity; mimic joints follow their masters). Cost (7.16):
weighted squared distances between mapped robot frames and the plan's goals, a small acceleration
penalty, and for hand-arm models the hand-pose regulariser (7.22). Constraints: joint limits
(7.17), a trust region per SQP iteration (7.18), velocity and acceleration limits (7.19),
workspace planes against collision spheres (7.20), and separating planes between convex shapes,
recomputed by coal GJK/EPA at every SQP iterate (7.21, collision.py).

Solver: Gauss-Newton SQP. Each iteration is one call of a CasADi SX function (Gauss-Newton Hessian,
gradient, constraints and their Jacobian in one sparse evaluation) and one QP solved by CasADi's
primal-dual interior-point QP ``ipqp`` (Mehrotra predictor-corrector, sparse LDL), as in the thesis;
docs/trajopt.md records the solver comparison behind that choice. Warm starts come from the
executing trajectory, which the receding-horizon caller shifts by the elapsed knots.
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from services.trajopt.calls import BUFFERED_QP, BufferedFunction, OrdinaryCall, qp_options
from services.trajopt.collision import CollisionModel
from services.trajopt.config import TrajoptConfig, TrajoptInputError, TrajoptResult
from shared.kinematics import RobotModel
from shared.robots.registry import REGISTRY

OCP_SOLVERS = ("hpipm", "fatrop")  # QP solvers that need (and exploit) the stage-wise layout


def default_point_map(model: RobotModel) -> dict[str, str]:
    """The described robot's point map (shared/robots); empty for a model without a description."""
    desc = REGISTRY.get(model.name)
    return dict(desc.point_map) if desc else {}


def default_pairs(model: RobotModel) -> list[tuple[str, str]]:
    """The described robot's collision pairs whose links this model has."""
    desc = REGISTRY.get(model.name)
    links = set(model.links)
    return [p for p in (desc.collision_pairs if desc else ()) if p[0] in links and p[1] in links]


class TrajectoryOptimizer:
    def __init__(self, model: RobotModel, config: TrajoptConfig | None = None) -> None:
        self.model = model
        self.cfg = cfg = config or TrajoptConfig()
        if not 1 <= cfg.fixed_knots < cfg.knots:
            raise ValueError(f"need 1 <= fixed_knots < knots, got {cfg.fixed_knots}, {cfg.knots}")
        self.n = len(model.joint_names)
        self.na = len(model.actuated)
        self.M, self.c = model.coupling
        self.act_index = [model.joint_names.index(j.name) for j in model.actuated]
        self.point_map = dict(cfg.point_map or default_point_map(model))
        missing = [f for f in self.point_map.values() if f not in model.frames()]
        if missing:
            raise ValueError(f"point_map names frames {missing} that {model.name} does not have")
        self.point_names = list(self.point_map)
        self.frames = [self.point_map[p] for p in self.point_names]
        self.weights = np.array([cfg.point_weights.get(p, 1.0) for p in self.point_names])
        self.collision = CollisionModel(model, default_pairs(model) if cfg.collision_pairs is None
                                        else cfg.collision_pairs, cfg.near)
        radii = cfg.sphere_radii if cfg.sphere_radii is not None else {k: 0.005 for k in model.keypoints}
        self.spheres = [(f, np.zeros(3), r) for f, r in radii.items()]
        self.spheres += [(s.link, s.origin[:3, 3], float(s.size[0])) for s in model.shapes if s.kind == "sphere"]
        self.slots = min(cfg.contact_slots, len(self.collision))
        self._limits()
        self.layout = "ocp" if cfg.qp_solver in OCP_SOLVERS else "compact"
        self._sample_workspace()
        self._build()
        self._warm = False  # the QP's dual start holds the last QP's multipliers
        # The last iterate's free knots and its separating planes: the next cycle starts from the
        # same configurations shifted by whole knots, so their planes need no second GJK/EPA pass.
        self._planes: tuple[np.ndarray, np.ndarray, np.ndarray, float, str] | None = None

    # --- problem data -------------------------------------------------------------------------
    def _limits(self) -> None:
        """Bounds of the independent joints: a master's limits intersected with those of its mimics,
        each narrowed by the configured margin (a range narrower than two margins: its middle)."""
        lo, hi, vel = self.model.lower.copy(), self.model.upper.copy(), self.model.max_velocity.copy()
        kinds = {j.name: j.kind for j in self.model.joints}
        margin = np.array([self.cfg.limit_margin_m if kinds.get(n) == "prismatic" else self.cfg.limit_margin_rad
                           for n in self.model.joint_names])
        bounded = np.isfinite(lo) & np.isfinite(hi)
        mid = np.where(bounded, (lo + hi) / 2, 0.0)
        lo = np.where(bounded, np.minimum(lo + margin, mid), lo)
        hi = np.where(bounded, np.maximum(hi - margin, mid), hi)
        alo, ahi, avel = lo[self.act_index], hi[self.act_index], vel[self.act_index]
        for i, j in enumerate(self.model.moving):
            if j.mimic is None:
                continue
            a = [jj.name for jj in self.model.actuated].index(j.mimic)
            m = j.multiplier
            if abs(m) > 1e-12:
                b = sorted(((lo[i] - j.offset) / m, (hi[i] - j.offset) / m))
                alo[a], ahi[a] = max(alo[a], b[0]), min(ahi[a], b[1])
                avel[a] = min(avel[a], vel[i] / abs(m))
        self.lower_a, self.upper_a, self.vmax_a = alo, ahi, avel
        self.amax_a = avel / self.cfg.accel_time

    def _sample_workspace(self, samples: int = 4000) -> None:
        """Reach box of each mapped frame and the (plane, sphere) pairs that can ever be active,
        from random joint vectors (half of them at corners of the joint box, where prismatic
        chains reach their extremes)."""
        rng = np.random.default_rng(0)
        lo = np.where(np.isfinite(self.lower_a), self.lower_a, -np.pi)
        hi = np.where(np.isfinite(self.upper_a), self.upper_a, np.pi)
        qa = rng.uniform(lo, hi, size=(samples, self.na))
        corner = rng.random((samples // 2, self.na)) < 0.5
        qa[: samples // 2] = np.where(corner, lo, hi)
        q = qa @ self.M.T + self.c
        q_s = ca.SX.sym("q", self.n)
        fk = self.model.fk_casadi(q_s)
        targets = [(f, np.zeros(3)) for f in self.frames] + [(f, loc) for f, loc, _ in self.spheres]
        pts_fn = ca.Function("pts", [q_s], [ca.horzcat(*[fk[f][0] @ ca.DM(loc) + fk[f][1] for f, loc in targets])])
        # map() concatenates the (3, T) outputs horizontally: (3, samples * T)
        pts = np.array(pts_fn.map(samples)(q.T)).reshape(3, samples, len(targets)).transpose(2, 1, 0)
        P = len(self.frames)
        self.reach_lo = pts[:P].min(axis=1) - self.cfg.reach_padding
        self.reach_hi = pts[:P].max(axis=1) + self.cfg.reach_padding
        self.active_planes = []  # (plane normal, offset, sphere index) that some pose can violate
        for normal, offset in self.cfg.planes:
            for i, (_, _, r) in enumerate(self.spheres):
                if (offset - r - pts[P + i] @ np.asarray(normal)).min() < 1e-3:
                    self.active_planes.append((normal, offset, i))

    def _build(self) -> None:
        """The SQP subproblem as one CasADi function. Layout "ocp" (for hpipm/fatrop) orders the
        variables stage-wise as x_k = (q_k, q_{k-1}), u_k = q_{k+1} with dynamics rows, so the QP has
        the optimal-control structure that Riccati-based interior-point solvers exploit; layout
        "compact" has only the q_k (for general sparse QP solvers)."""
        cfg, na, K, F = self.cfg, self.na, self.cfg.knots, self.cfg.fixed_knots
        Kf, P = K - F, len(self.frames)
        N = Kf - 1
        ocp = self.layout == "ocp"
        nz = Kf * 2 * na + N * na if ocp else Kf * na
        z = ca.SX.sym("z", nz)
        fixed = ca.SX.sym("fixed", F * na)
        goals = ca.SX.sym("goals", Kf * P * 3)
        w = ca.SX.sym("w", Kf * P)
        dt = ca.SX.sym("dt")
        S, L = self.slots, len(self.collision.links)
        # per knot and contact slot: normal, witness a and b (in their link frames), one-hot link a, link b
        wit = ca.SX.sym("wit", Kf * S * (9 + 2 * L))
        # only links that are side a (b) of some pair can have a one-hot entry there: the other terms
        # are zero, and leaving them out halves the slot rows' part of the function for the workcell
        links = self.collision.links
        side_a, side_b = sorted(set(self.collision.link_a.tolist())), sorted(set(self.collision.link_b.tolist()))
        fixed_q = [fixed[k * na:(k + 1) * na] for k in range(F)]
        stride = 3 * na
        if ocp:
            q_idx = [np.arange(k * stride, k * stride + na) for k in range(Kf)]
            p_idx = [np.arange(k * stride + na, k * stride + 2 * na) for k in range(Kf)]
            u_idx = [np.arange(k * stride + 2 * na, k * stride + 3 * na) for k in range(N)]
        else:
            q_idx = [np.arange(k * na, (k + 1) * na) for k in range(Kf)]
            p_idx, u_idx = [], []
        qv = [z[list(i)] for i in q_idx]

        def prev(kf: int, back: int = 1):
            j = kf - back
            if j >= 0:
                return z[list(p_idx[kf])] if (ocp and back == 1) else qv[j]
            if ocp and back == 1:
                return z[list(p_idx[kf])]  # a copy of the last fixed knot, pinned by its bounds
            return fixed_q[F + j]

        def nxt(kf: int):
            return z[list(u_idx[kf])] if ocp else qv[kf + 1]

        M, c = ca.DM(self.M), ca.DM(self.c)
        fk = self.model._fk_function
        frames = self.model.frames()
        mean_idx = [(self.model.joint_names.index(j), mu, cfg.pose_std.get(j, 1.0)) for j, mu in cfg.pose_mean.items()]
        res, cons, lbg, ubg, labels, pose_out, ng = [], [], [], [], [], [], []
        self._slot_rows: list[int] = []

        def add(expr, lo, hi, label: str) -> None:
            cons.append(expr)
            size = expr.numel()
            lbg.extend(np.broadcast_to(lo, size))
            ubg.extend(np.broadcast_to(hi, size))
            labels.extend([label] * size)

        for kf in range(Kf):
            k = kf + F
            if ocp and kf < N:  # dynamics out of this stage first (HPIPM's row order): u_k = q_{k+1}, q_k = p_{k+1}
                add(z[list(u_idx[kf])] - qv[kf + 1], 0.0, 0.0, "dynamics")
                add(qv[kf] - z[list(p_idx[kf + 1])], 0.0, 0.0, "dynamics")
            rows0 = len(lbg)
            q_full = ca.mtimes(M, qv[kf]) + c
            out = fk(q_full)
            pose = {f: (out[2 * i], out[2 * i + 1]) for i, f in enumerate(frames)}
            for i, f in enumerate(self.frames):  # 7.16
                j = kf * P + i
                res.append(ca.sqrt(w[j]) * (pose[f][1] - goals[3 * j:3 * j + 3]))
            for idx, mu, sd in mean_idx:  # 7.22
                res.append(np.sqrt(cfg.pose_weight) * (q_full[idx] - mu) / sd)
            for normal, offset, i in self.active_planes:  # 7.20
                frame, local, r = self.spheres[i]
                R, p = pose[frame]
                add(ca.dot(ca.DM(normal), p + ca.mtimes(R, ca.DM(local))), -np.inf, offset - r,
                    f"workspace plane for {frame} at knot {k}")
            for i in range(S):  # 7.21, the S closest shape pairs at this knot
                v = wit[(kf * S + i) * (9 + 2 * L):(kf * S + i + 1) * (9 + 2 * L)]
                wa = sum(v[9 + j] * (pose[links[j]][1] + ca.mtimes(pose[links[j]][0], v[3:6])) for j in side_a)
                wb = sum(v[9 + L + j] * (pose[links[j]][1] + ca.mtimes(pose[links[j]][0], v[6:9])) for j in side_b)
                self._slot_rows.append(len(lbg))
                add(ca.dot(v[:3], wb - wa), cfg.margin, np.inf, f"separation slot {i} at knot {k}")
            for link in self.collision.links:
                R, p = pose[link]
                pose_out.append(ca.reshape(ca.horzcat(R, p), 12, 1))
            add((qv[kf] - prev(kf)) / dt, -self.vmax_a, self.vmax_a, f"velocity limit at knot {k}")  # 7.19
            if kf == 0 and F >= 2:
                acc = (qv[0] - 2 * prev(0) + fixed_q[F - 2]) / dt ** 2
                add(acc, -self.amax_a, self.amax_a, f"acceleration limit at knot {k - 1}")
                res.append(np.sqrt(cfg.smooth_weight) * acc * dt)
            if kf < N:
                acc = (nxt(kf) - 2 * qv[kf] + prev(kf)) / dt ** 2
                add(acc, -self.amax_a, self.amax_a, f"acceleration limit at knot {k}")
                res.append(np.sqrt(cfg.smooth_weight) * acc * dt)
            ng.append(len(lbg) - rows0)
        r = ca.vertcat(*res)
        g = ca.vertcat(*cons)
        J = ca.jacobian(r, z)
        G = ca.jacobian(g, z)
        H = ca.mtimes(J.T, J) + cfg.damping * ca.SX.eye(nz)  # Levenberg-Marquardt: flat directions take small steps
        params = [fixed, goals, w, dt, wit]
        cost = 0.5 * ca.sumsqr(r)
        self._eval = ca.Function("trajopt_sqp", [z, *params], [H, ca.mtimes(J.T, r), g, G, cost])
        # g and the cost alone: the convergence test and the final check need no derivatives
        self._check = ca.Function("trajopt_check", [z, *params], [g, cost])
        self._poses = ca.Function("trajopt_poses", [z], [ca.vertcat(*pose_out) if pose_out else ca.SX(0, 1)])
        self._lbg, self._ubg, self._labels = np.array(lbg, float), np.array(ubg, float), labels
        self._slot_rows = np.array(self._slot_rows, int).reshape(Kf, S)
        self._smooth_rows = np.ones(len(lbg), bool)  # rows with a fixed meaning and finite bounds
        self._smooth_rows[self._slot_rows.ravel()] = False
        self._smooth_rows &= np.isfinite(self._lbg) | np.isfinite(self._ubg)
        self._H_sp, self._G_sp = H.sparsity(), G.sparsity()
        self.q_index = np.concatenate(q_idx)
        self.nz = nz
        # z from the stacked free-knot q's: every copy (q, p, u) of a knot gets the same value
        self._expand = np.zeros(nz, int)
        for kf in range(Kf):
            self._expand[q_idx[kf]] = kf * na + np.arange(na)
            if ocp and kf > 0:
                self._expand[p_idx[kf]] = (kf - 1) * na + np.arange(na)
            if ocp and kf < N:
                self._expand[u_idx[kf]] = (kf + 1) * na + np.arange(na)
        self._p0 = p_idx[0] if ocp else np.zeros(0, int)  # copy of the last fixed knot
        q_s = ca.SX.sym("q", self.n)
        fk_s = self.model.fk_casadi(q_s)
        self._points = ca.Function("points", [q_s], [ca.horzcat(*[fk_s[f][1] for f in self.frames]).T])
        opts = {**qp_options(cfg.qp_solver), **cfg.qp_options}
        if ocp:
            opts.update(N=N, nx=[2 * na] * Kf, nu=[na] * N + [0], ng=ng)
            if cfg.qp_solver == "fatrop":
                opts["structure_detection"] = "manual"
        self._qp = ca.conic("trajopt_qp", cfg.qp_solver, {"h": self._H_sp, "a": self._G_sp}, opts)
        self._bind()

    def _bind(self) -> None:
        """Buffered calls of the functions a solve evaluates; the linearisation writes H, the
        gradient and G straight into the QP's input arrays."""
        self._qp_call = qp = BufferedFunction(self._qp) if self.cfg.qp_solver in BUFFERED_QP else OrdinaryCall(self._qp)
        self._qp_in = {name: qp.args[i] for i, name in enumerate(self._qp.name_in())}
        self._qp_out = {name: qp.res[i] for i, name in enumerate(self._qp.name_out())}
        self._lin = BufferedFunction(self._eval)
        self._lin_copies = []  # (output, QP input, index of each input nonzero among the output's or -1)
        for i, name in ((0, "h"), (1, "g"), (3, "a")):
            sp_out, sp_in = self._eval.sparsity_out(i), self._qp.sparsity_in(self._qp.index_in(name))
            if sp_out == sp_in:
                self._lin.bind_res(i, self._qp_in[name])
            else:  # some plugins (hpipm) take another pattern: copy the matching nonzeros
                pos = {rc: k for k, rc in enumerate(zip(*sp_out.get_triplet(), strict=True))}
                idx = np.array([pos.get(rc, -1) for rc in zip(*sp_in.get_triplet(), strict=True)], int)
                self._lin_copies.append((self._lin.res[i], self._qp_in[name], idx))
        self._check_call = BufferedFunction(self._check)
        self._poses_call = BufferedFunction(self._poses)
        self._G_nz = self._lin.res[3]
        # G's nonzeros in CasADi's column-major order: row and column of each, for G @ dz
        self._G_rows = np.array(self._G_sp.row(), int)
        self._G_cols = np.repeat(np.arange(self._G_sp.size2()), np.diff(self._G_sp.colind()))

    # --- helpers ------------------------------------------------------------------------------------
    def points(self, q: np.ndarray) -> np.ndarray:
        """Mapped frame positions (P, 3) for a full joint vector."""
        return np.array(self._points(self.model.couple(q)))

    def _link_poses(self, z: np.ndarray) -> dict[str, np.ndarray]:
        L, Kf = len(self.collision.links), self.cfg.knots - self.cfg.fixed_knots
        if not L:
            return {}
        raw = self._poses_call(z)[0]
        T = np.zeros((Kf, L, 4, 4))
        T[..., :3, :] = raw.reshape(Kf, L, 4, 3).transpose(0, 1, 3, 2)  # column-major 3x4 blocks
        T[..., 3, 3] = 1.0
        return {link: T[:, i] for i, link in enumerate(self.collision.links)}

    def _witness_vector(self, z: np.ndarray, final: bool = False) -> tuple[np.ndarray, np.ndarray, float, str]:
        """Separating planes of the closest shape pairs per knot (the QP's contact slots), the lower
        bound of each slot row (-inf for an unused slot), and the smallest signed distance over all
        pairs with its name (for the final check; a lower bound for pairs far apart)."""
        Kf, S, L = self.cfg.knots - self.cfg.fixed_knots, self.slots, len(self.collision.links)
        lb = self._lbg.copy()
        if not S:
            return np.zeros(0), lb, np.inf, ""
        poses = self._link_poses(z)
        if final:  # also exact wherever the sphere bound cannot prove the margin (the final check)
            wit = self.collision.witnesses(poses, per_knot=S, always_below=self.cfg.margin + 1e-6)
        else:  # GJK/EPA for the closest candidates that get a slot
            wit = self.collision.witnesses(poses, per_knot=S)
        order = np.argsort(wit.distance, axis=0)[:S]  # (S', Kf): the closest pairs per knot
        k = np.arange(Kf)[None]
        v = np.zeros((Kf, S, 9 + 2 * L))
        used = np.zeros((Kf, S), bool)
        Sp = order.shape[0]
        v[:, :Sp, 0:3] = wit.normal[order, k].transpose(1, 0, 2)
        v[:, :Sp, 3:6] = wit.local_a[order, k].transpose(1, 0, 2)
        v[:, :Sp, 6:9] = wit.local_b[order, k].transpose(1, 0, 2)
        kk, ss = np.meshgrid(np.arange(Kf), np.arange(Sp), indexing="ij")
        v[kk, ss, 9 + self.collision.link_a[order.T]] = 1.0
        v[kk, ss, 9 + L + self.collision.link_b[order.T]] = 1.0
        used[:, :Sp] = True
        lb[self._slot_rows[~used]] = -np.inf
        i, k = np.unravel_index(np.argmin(wit.distance), wit.distance.shape)
        pr = self.collision.pairs[i]
        name = f"separation {pr.a.link}-{pr.b.link} at knot {k + self.cfg.fixed_knots}"
        return v.ravel(), lb, float(wit.distance[i, k]), name

    def _shifted_planes(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, str] | None:
        """The last iterate's planes when z's free knots are its knots shifted by a whole number of
        knots (the padded tail repeating its last knot), else None. Exact reuse: same configurations,
        same planes."""
        if self._planes is None or not len(self._slot_rows):
            return None
        qa_old, wit_old, lb_old, dmin, pair = self._planes
        Kf = len(qa_old)
        qa = z[self.q_index].reshape(qa_old.shape)
        for shift in range(Kf):
            src = np.minimum(np.arange(Kf) + shift, Kf - 1)
            if np.array_equal(qa, qa_old[src]):
                wit = wit_old.reshape(Kf, -1)[src].ravel()
                lb = lb_old.copy()
                lb[self._slot_rows] = lb_old[self._slot_rows[src]]
                return wit, lb, dmin, pair
        return None

    def _fail(self, current: np.ndarray, status: str, reason: str, t0: float, iterations: int = 0,
              violation: float = float("nan")) -> TrajoptResult:
        return TrajoptResult(current.copy(), status, False, time.perf_counter() - t0, iterations, violation, reason)

    # --- solve ------------------------------------------------------------------------------------
    def solve(self, current_traj: np.ndarray, goals: np.ndarray, goal_mask: np.ndarray, dt: float) -> TrajoptResult:
        """current_traj: (knots, n) executing trajectory (its first fixed_knots rows are kept);
        goals: (knots, points, 3) in ``point_names`` order; goal_mask: (knots, points), False = ignore.
        Never raises on bad values (NaN, unreachable, infeasible, a failed QP): returns ok=False, the
        executing trajectory unchanged and a reason. Wrong shapes raise TrajoptInputError."""
        t0 = time.perf_counter()
        cfg, na, K, F = self.cfg, self.na, self.cfg.knots, self.cfg.fixed_knots
        P = len(self.frames)
        current = np.asarray(current_traj, float)
        if current.shape != (K, self.n):
            raise TrajoptInputError(f"current trajectory has shape {current.shape}, expected {(K, self.n)}")
        goals = np.asarray(goals, float)
        mask = np.asarray(goal_mask, bool)
        if goals.shape != (K, P, 3) or mask.shape != (K, P):
            raise TrajoptInputError(f"goals {goals.shape} / mask {mask.shape}, expected {(K, P, 3)} / {(K, P)}")
        if not np.isfinite(current).all():
            return self._fail(current, "bad_input", "current trajectory contains NaN or infinite values", t0)
        if not (np.isfinite(dt) and dt > 0):
            return self._fail(current, "bad_input", f"dt must be positive, got {dt}", t0)
        bad = ~np.isfinite(goals).all(axis=-1) & mask
        if bad.any():
            k, i = np.argwhere(bad)[0]
            return self._fail(current, "bad_input", f"goal {self.point_names[i]} at knot {k} is NaN or infinite "
                                                    f"({int(bad.sum())} such goals)", t0)
        goals = np.where(mask[..., None], goals, 0.0)
        out = mask & ((goals < self.reach_lo[None]) | (goals > self.reach_hi[None])).any(axis=-1)
        out[:F] = False
        if out.any():
            k, i = np.argwhere(out)[0]
            return self._fail(current, "unreachable",
                              f"goal {self.point_names[i]} -> {self.frames[i]} at knot {k} "
                              f"{np.round(goals[k, i], 3).tolist()} lies outside the reachable box "
                              f"{np.round(self.reach_lo[i], 3).tolist()}..{np.round(self.reach_hi[i], 3).tolist()}", t0)
        qa_cur = current[:, self.act_index]
        fixed = qa_cur[:F].ravel()
        lo_q, hi_q = np.tile(self.lower_a, K - F), np.tile(self.upper_a, K - F)
        z = np.clip(qa_cur[F:].ravel(), lo_q, hi_q)[self._expand]
        lo_z, hi_z = lo_q[self._expand], hi_q[self._expand]
        if len(self._p0):  # the stage-0 copy of the last fixed knot is pinned by its bounds
            z[self._p0] = lo_z[self._p0] = hi_z[self._p0] = qa_cur[F - 1]
        weights = (mask[F:] * self.weights[None]).ravel()
        gvec = goals[F:].ravel()
        status, it, cost = "max_iterations", 0, float("nan")
        wit, lbg, dmin, pair = self._shifted_planes(z) or self._witness_vector(z)
        params = (fixed, gvec, weights, dt)
        # H, the gradient and G land in the QP's inputs; g and the cost are copied (the next call overwrites them)
        _, _, g, _, cost = self._linearise(z, params, wit)
        g, cost = g.copy(), float(cost[0])
        qp_in, qp_out = self._qp_in, self._qp_out
        for it in range(1, cfg.max_iterations + 1):
            np.maximum(lo_z - z, -cfg.trust_region, out=qp_in["lbx"])  # 7.17 and 7.18
            np.minimum(hi_z - z, cfg.trust_region, out=qp_in["ubx"])
            np.subtract(lbg, g, out=qp_in["lba"])
            np.subtract(self._ubg, g, out=qp_in["uba"])
            failure = self._solve_qp()
            if failure:  # a failed QP is never read as a (converged) step: keep the executing one
                self._warm = False
                v, what = self._violation(z, g, lbg, dmin, pair, lo_z, hi_z)  # a likely cause
                why = f"{failure}; the iterate violates {what} by {v:.4g}" if v > cfg.violation_tolerance else failure
                return self._fail(current, "qp_failed", f"kept the executing trajectory: QP ({cfg.qp_solver}) "
                                                         f"failed in SQP iteration {it}: {why}", t0, it, v)
            dz = qp_out["x"].copy()
            decrease = -float(qp_out["cost"][0])  # the Gauss-Newton model's predicted cost decrease
            predicted_cost = cost - decrease
            predicted_g = g + np.bincount(self._G_rows, self._G_nz * dz[self._G_cols], len(g))  # g + G dz
            z = z + dz
            # the next linearisation point; this pass is also the final check of the last iterate
            wit, lbg, dmin, pair = self._witness_vector(z, final=True)
            self._planes = (z[self.q_index].reshape(K - F, na).copy(), wit, lbg, dmin, pair)
            g, cost = self._check_call(z, *params, wit)
            g, cost = g.copy(), float(cost[0])
            # Converged when the step stayed inside the trust region and the QP model predicted the
            # cost and constraints at the new iterate (then its solution is the local optimum).
            inside = np.all(np.abs(dz) < cfg.trust_region * 0.999)
            model_err = abs(cost - predicted_cost)
            # separation rows are re-assigned to the closest pairs at every iterate: not comparable
            g_err = np.abs(g - predicted_g)[self._smooth_rows]
            if np.abs(dz).max() < cfg.step_tolerance or (
                    inside and model_err <= cfg.model_tolerance * max(decrease, 0.0) + 1e-9
                    and (g_err.max(initial=0.0) < cfg.step_tolerance)):
                status = "solved"
                break
            if it < cfg.max_iterations:  # derivatives only where another QP follows
                self._linearise(z, params, wit)
        violation, what = self._violation(z, g, lbg, dmin, pair, lo_z, hi_z)
        if violation > cfg.violation_tolerance:
            return self._fail(current, "infeasible", f"kept the executing trajectory: {what} violated by "
                                                     f"{violation:.4g} after {it} SQP iterations", t0, it, violation)
        qa = z[self.q_index].reshape(K - F, na)
        q = np.vstack([current[:F], qa @ self.M.T + self.c])
        return TrajoptResult(q, status, True, time.perf_counter() - t0, it, violation, "", cost)

    def _linearise(self, z: np.ndarray, params: tuple, wit: np.ndarray) -> list[np.ndarray]:
        out = self._lin(z, *params, wit)
        for src, dst, idx in self._lin_copies:
            dst[:] = np.where(idx >= 0, src[idx], 0.0)
        return out

    def _solve_qp(self) -> str:
        """Solve the QP whose inputs are in ``_qp_in``: "" on success (the step in ``_qp_out``), or
        why it failed: the plugin's own verdict (``stats()["success"]``, its return status), an
        exception, or a non-finite step. Plugins run with error_on_fail=False, so a failed solve
        returns some vector (often small, or the initial guess), which the SQP would otherwise take
        for a converged step. The duals start from the last successful QP's (``_warm``)."""
        if not self._warm:
            self._qp_in["lam_x0"][:] = 0.0
            self._qp_in["lam_a0"][:] = 0.0
        try:
            self._qp_call()
        except RuntimeError as exc:
            lines = str(exc).strip().splitlines()
            return f"raised {lines[-1][:200] if lines else type(exc).__name__}"
        stats = self._qp_call.stats()
        if not stats.get("success", False):
            return str(stats.get("return_status") or stats.get("unified_return_status") or "no success flag")
        if not np.isfinite(self._qp_out["x"]).all():
            return "non-finite step"
        self._qp_in["lam_x0"][:] = self._qp_out["lam_x"]
        self._qp_in["lam_a0"][:] = self._qp_out["lam_a"]
        self._warm = True
        return ""

    def _violation(self, z, g, lbg, dmin, pair, lo_z, hi_z) -> tuple[float, str]:
        """Largest constraint violation at z and what it is: the rows evaluated at z (separation
        rows are signed distances there), every shape pair's distance, joint limits."""
        rows = np.maximum(lbg - g, g - self._ubg)
        cands = [(max(0.0, (lo_z - z).max(), (z - hi_z).max()), "joint limits"),
                 (self.cfg.margin - dmin, pair)]
        if len(rows):
            cands.append((float(rows.max()), self._labels[int(np.argmax(rows))]))
        v, what = max(cands, key=lambda c: c[0])
        return max(float(v), 0.0), what

    def reset(self) -> None:
        """Forget the QP warm start and the last planes (after a jump in the executing trajectory)."""
        self._warm = False
        self._planes = None
