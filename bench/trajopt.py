"""P3: receding-horizon trajectory optimization on the workcell (10 joints, 1 s horizon, 20 knots,
separating planes between the arms): the kept formulation (Gauss-Newton SQP, CasADi SX function +
ipqp interior-point QP, configured as the trajopt service runs it) against the plain casadi.Opti +
IPOPT formulation of the same problem, both warm-started, measured in the same run on one thread.
Writes .bench/trajopt.json. Target: p95 <= 10 ms and >= 3x faster than the plain formulation.

The scenario: the left gripper circles over the table while the right finger sweeps towards it
and back, so the arms come within a few centimetres in the middle of the sequence. The kept
solver runs it in closed loop once; that fixes the sequence of problems (executing trajectory =
warm start, goals, separating planes from the same GJK/EPA call). Every alternative then solves
exactly that sequence, interleaved (problem k by every alternative before problem k+1, so a change
in machine load hits all of them alike), each keeping its own dual warm start from its previous
solve. Every returned trajectory is checked by the same code: the optimizer's constraint rows,
exact GJK/EPA distances of all shape pairs, and the goal error at the last knot.

``--compare`` adds the other solvers in the installed CasADi (QP plugins inside the SQP, IPOPT with
expand, sqpmethod with qpOASES / HPIPM, FATROP, a stage-wise Opti formulation those need);
``--jit`` adds code-generated variants (compile time reported separately). docs/trajopt.md has
the table and the reasons for the choice.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import casadi as ca  # noqa: E402
import numpy as np  # noqa: E402
from _trajopt_report import summarize, table  # noqa: E402  (bench/, beside this script)

from services.trajopt.optimizer import TrajectoryOptimizer, TrajoptConfig  # noqa: E402
from services.trajopt.service import TrajoptService  # noqa: E402
from shared.kinematics import load_robot  # noqa: E402

STEPS, WARMUP = 80, 5
SERVICE = TrajoptService.Params()
DT = SERVICE.horizon_s / SERVICE.knots


def deployed_config(**kw) -> TrajoptConfig:
    """The optimizer as the trajopt service builds it for the workcell (no hand-pose prior there)."""
    return TrajoptConfig(knots=SERVICE.knots, fixed_knots=SERVICE.fixed_knots,
                         max_iterations=SERVICE.max_iterations, **kw)


def start() -> np.ndarray:
    q = np.zeros(10)
    q[[1, 7]] = -0.01, 0.0  # left carriage at y = 0.14, right at -0.15
    q[[2, 8]] = 0.15
    return q


def goals_at(opt: TrajectoryOptimizer, step: int, K: int) -> np.ndarray:
    t = (step + np.arange(K)) * DT
    base = opt.points(start())
    g = np.repeat(base[None], K, 0)
    circle = np.stack([0.05 * np.sin(1.5 * t), 0.03 * np.cos(1.5 * t), -0.04 + 0.02 * np.sin(2 * t)], -1)
    g[:, :2] += circle[:, None]
    sweep = 0.5 - 0.5 * np.cos(2 * np.pi * t / 4.0)  # 0 -> 1 -> 0 over 4 s
    g[:, 2] += np.stack([0.03 * np.sin(t), 0.21 * sweep, -0.06 * sweep], -1)  # reaches y = +0.08
    return g


@dataclass
class Problem:
    current: np.ndarray  # (K, n) executing trajectory: fixed knots + warm start
    goals: np.ndarray  # (K, P, 3)


@dataclass
class Outcome:
    q: np.ndarray  # (K, n)
    iterations: int
    ok: bool  # the solver's own verdict (ours: ok; Opti: stats()["success"])
    status: str = ""


def record_sequence(model, steps: int) -> list[Problem]:
    """The closed-loop run of the kept solver: the problems every alternative solves."""
    opt = TrajectoryOptimizer(model, deployed_config())
    K = opt.cfg.knots
    cur = np.repeat(start()[None], K, 0)
    mask = np.ones((K, len(opt.frames)), bool)
    seq = []
    for step in range(steps):
        goals = goals_at(opt, step, K)
        seq.append(Problem(cur.copy(), goals))
        r = opt.solve(cur, goals, mask, DT)
        cur = np.concatenate([r.q[1:], r.q[-1:]])  # receding horizon: one knot per step
    return seq


# --- alternatives --------------------------------------------------------------------------------
class Ours:
    """The project's optimizer (services/trajopt/optimizer.py) with a given QP plugin."""

    kind = "GN-SQP"

    def __init__(self, model, qp_solver: str = "ipqp", qp_options: dict | None = None) -> None:
        self.opt = TrajectoryOptimizer(model, deployed_config(qp_solver=qp_solver, qp_options=qp_options or {}))
        self.mask = np.ones((self.opt.cfg.knots, len(self.opt.frames)), bool)

    def solve(self, p: Problem) -> Outcome:
        r = self.opt.solve(p.current, p.goals, self.mask, DT)
        return Outcome(r.q, r.iterations, r.ok, "" if r.ok else r.reason)


def codegen(opt: TrajectoryOptimizer, flags: list[str], workdir: Path) -> float:
    """Replace the optimizer's CasADi SX functions (the SQP linearisation, the final check, link
    poses) by C code compiled with gcc; returns the seconds spent generating and compiling."""
    t0 = time.perf_counter()
    for attr in ("_eval", "_check", "_poses"):
        f = getattr(opt, attr)
        src = workdir / f"{f.name()}.c"
        lib = workdir / f"{f.name()}.so"
        gen = ca.CodeGenerator(src.name, {"with_header": False})
        gen.add(f)
        gen.generate(str(workdir) + "/")
        subprocess.run(["gcc", *flags, "-fPIC", "-shared", str(src), "-o", str(lib)], check=True)
        setattr(opt, attr, ca.external(f.name(), str(lib)))
    opt._bind()  # a solve calls the buffered functions: rebuild them from the compiled ones
    return time.perf_counter() - t0


class PlainOpti:
    """The same problem written directly with casadi.Opti: cost 7.16 + the same smoothing, joint,
    velocity and acceleration limits, workspace planes, and the same separating planes (GJK/EPA at
    the warm start, held during the solve, since Opti cannot call coal inside the NLP solver's
    iterations). Variables: the free knots' independent joints."""

    kind = "Opti"

    def __init__(self, opt: TrajectoryOptimizer, solver: str = "ipopt", options: dict | None = None) -> None:
        self.opt = opt
        cfg, na, K, F = opt.cfg, opt.na, opt.cfg.knots, opt.cfg.fixed_knots
        Kf, P, S, L = K - F, len(opt.frames), opt.slots, len(opt.collision.links)
        o = self.o = ca.Opti()
        self.Q = o.variable(na, Kf)
        self.fixed = o.parameter(na, F)
        self.goals = o.parameter(3, Kf * P)
        self.wit = o.parameter(9 + 2 * L, Kf * S)
        cols = [self.fixed[:, k] for k in range(F)] + [self.Q[:, k] for k in range(Kf)]
        cost = 0
        for kf in range(Kf):
            q = cols[F + kf]
            cost += self._stage(q, kf)
            o.subject_to(o.bounded(opt.lower_a, q, opt.upper_a))
            o.subject_to(o.bounded(-opt.vmax_a * DT, q - cols[F + kf - 1], opt.vmax_a * DT))
        for k in range(max(1, F - 1), K - 1):
            acc = (cols[k + 1] - 2 * cols[k] + cols[k - 1]) / DT ** 2
            o.subject_to(o.bounded(-opt.amax_a, acc, opt.amax_a))
            cost += 0.5 * cfg.smooth_weight * ca.sumsqr(acc * DT)
        o.minimize(cost)
        o.solver(solver, options or {})
        self.lam = None

    def _stage(self, q, kf: int):
        """Tracking cost of knot kf and its plane and separation rows (7.16, 7.20, 7.21)."""
        opt, o = self.opt, self.o
        P, S, L = len(opt.frames), opt.slots, len(opt.collision.links)
        fk = opt.model.fk_casadi(ca.DM(opt.M) @ q + ca.DM(opt.c))
        cost = 0
        for i, f in enumerate(opt.frames):
            cost += 0.5 * opt.weights[i] * ca.sumsqr(fk[f][1] - self.goals[:, kf * P + i])
        for normal, offset, i in opt.active_planes:
            frame, local, r = opt.spheres[i]
            o.subject_to(ca.dot(ca.DM(normal), fk[frame][1] + fk[frame][0] @ ca.DM(local)) <= offset - r)
        for s in range(S):
            v = self.wit[:, kf * S + s]
            wa = sum(v[9 + j] * (fk[lk][1] + fk[lk][0] @ v[3:6]) for j, lk in enumerate(opt.collision.links))
            wb = sum(v[9 + L + j] * (fk[lk][1] + fk[lk][0] @ v[6:9]) for j, lk in enumerate(opt.collision.links))
            o.subject_to(ca.dot(v[:3], wb - wa) >= opt.cfg.margin)
        return cost

    def _set(self, p: Problem) -> np.ndarray:
        opt, F = self.opt, self.opt.cfg.fixed_knots
        qa = p.current[:, opt.act_index]
        z = qa[F:].ravel()[opt._expand]
        wit = opt._witness_vector(z)[0].reshape(-1, 9 + 2 * len(opt.collision.links)).T
        self.o.set_value(self.fixed, qa[:F].T)
        self.o.set_value(self.goals, p.goals[F:].reshape(-1, 3).T)
        self.o.set_value(self.wit, wit)
        return qa

    def _initial(self, qa: np.ndarray) -> None:
        self.o.set_initial(self.Q, qa[self.opt.cfg.fixed_knots:].T)

    def _value(self, value) -> np.ndarray:
        return np.asarray(value(self.Q)).reshape(self.opt.na, -1).T

    def solve(self, p: Problem) -> Outcome:
        opt, F = self.opt, self.opt.cfg.fixed_knots
        qa = self._set(p)
        self._initial(qa)
        if self.lam is not None:
            self.o.set_initial(self.o.lam_g, self.lam)
        try:
            sol = self.o.solve()
            self.lam = sol.value(self.o.lam_g)
            q = self._value(sol.value)
        except RuntimeError:  # the solver failed; its last iterate
            try:
                q = self._value(self.o.debug.value)
            except RuntimeError:  # not even an iterate (an exception inside the solver)
                q = qa[F:]
        try:
            stats = self.o.stats()
        except RuntimeError as exc:  # sqpmethod's stats() can raise after a failed QP
            stats = {"return_status": (str(exc).strip().splitlines() or ["stats() raised"])[-1][:200]}
        ok = bool(stats.get("success", False))
        status = str(stats.get("return_status", ""))
        if not ok and "unified_return_status" in stats:  # sqpmethod can leave a stale "Solve_Succeeded" there
            status = f"{status} / {stats['unified_return_status']}"
        return Outcome(np.vstack([p.current[:F], q @ opt.M.T + opt.c]), int(stats.get("iter_count", -1)), ok, status)


class StagewiseOpti(PlainOpti):
    """The same problem in the stage-wise form FATROP and HPIPM need: state x_k = (q_k, v_k) per
    free knot (v_k the backward-difference velocity), control u_k = acceleration, gap-closing
    x_{k+1} = (q_k + dt v_k + dt^2 u_k, v_k + dt u_k) first in every stage, then the stage's own
    rows. Same feasible set and cost as PlainOpti (the finite differences are the same)."""

    def __init__(self, opt: TrajectoryOptimizer, solver: str, options: dict | None = None) -> None:
        self.opt = opt
        cfg, na, K, F = opt.cfg, opt.na, opt.cfg.knots, opt.cfg.fixed_knots
        Kf, P, S, L = K - F, len(opt.frames), opt.slots, len(opt.collision.links)
        N = Kf - 1
        o = self.o = ca.Opti()
        self.X, self.U = [], []
        for k in range(Kf):  # declaration order = variable order: x0 u0 x1 u1 ... xN
            self.X.append(o.variable(2 * na))
            if k < N:
                self.U.append(o.variable(na))
        self.fixed = o.parameter(na, F)
        self.goals = o.parameter(3, Kf * P)
        self.wit = o.parameter(9 + 2 * L, Kf * S)
        cost = 0
        for k in range(Kf):
            q, v = self.X[k][:na], self.X[k][na:]
            if k < N:
                a = self.U[k]
                o.subject_to(self.X[k + 1] - ca.vertcat(q + DT * v + DT ** 2 * a, v + DT * a) == 0)
            if k == 0:
                o.subject_to(v - (q - self.fixed[:, F - 1]) / DT == 0)
                if F >= 2:
                    acc = (v - (self.fixed[:, F - 1] - self.fixed[:, F - 2]) / DT) / DT
                    o.subject_to(o.bounded(-opt.amax_a, acc, opt.amax_a))
                    cost += 0.5 * cfg.smooth_weight * ca.sumsqr(acc * DT)
            o.subject_to(o.bounded(opt.lower_a, q, opt.upper_a))
            o.subject_to(o.bounded(-opt.vmax_a, v, opt.vmax_a))
            if k < N:
                o.subject_to(o.bounded(-opt.amax_a, self.U[k], opt.amax_a))
                cost += 0.5 * cfg.smooth_weight * ca.sumsqr(self.U[k] * DT)
            cost += self._stage(q, k)
        o.minimize(cost)
        o.solver(solver, options or {})
        self.lam = None

    def _initial(self, qa: np.ndarray) -> None:
        F = self.opt.cfg.fixed_knots
        v = np.diff(qa, axis=0) / DT
        a = np.diff(qa, 2, axis=0) / DT ** 2
        for k, x in enumerate(self.X):
            self.o.set_initial(x, np.concatenate([qa[F + k], v[F + k - 1]]))
        for k, u in enumerate(self.U):
            self.o.set_initial(u, a[F + k - 1])

    def _value(self, value) -> np.ndarray:
        return np.array([np.asarray(value(x)).ravel()[:self.opt.na] for x in self.X])


IPOPT = {"print_level": 0, "sb": "yes", "warm_start_init_point": "yes"}
QUIET_SQP = {"print_time": False, "print_header": False, "print_iteration": False, "print_status": False,
             "error_on_fail": False, "convexify_strategy": "eigen-clip", "max_iter": 50}


def alternatives(model, compare: bool, jit: bool, jit_flags: list[str], workdir: Path) -> dict:
    """name -> (description, factory(first problem) returning (solver, compile seconds or None))."""
    base = lambda: TrajectoryOptimizer(model, deployed_config())  # noqa: E731
    alts = {
        "ours": ("GN-SQP + ipqp (kept)", lambda p: (Ours(model), None)),
        "plain_opti_ipopt": ("Opti + IPOPT (plain)", lambda p: (PlainOpti(base(), "ipopt", {
            "print_time": False, "ipopt": IPOPT}), None)),
    }
    if compare:
        for qp, opts in (("osqp", {}), ("qpoases", {"printLevel": "none"}), ("hpipm", {}), ("daqp", {}),
                         ("proxqp", {}), ("highs", {}), ("qrqp", {}), ("fatrop", {})):
            alts[f"sqp_{qp}"] = (f"GN-SQP + {qp}" + (" (stage-wise layout)" if qp in ("hpipm", "fatrop") else ""),
                                 lambda p, qp=qp, opts=opts: (Ours(model, qp, opts), None))
        alts["opti_ipopt_expand"] = ("Opti + IPOPT, expand=True", lambda p: (PlainOpti(base(), "ipopt", {
            "print_time": False, "expand": True, "ipopt": IPOPT}), None))
        alts["stagewise_ipopt"] = ("stage-wise Opti + IPOPT", lambda p: (StagewiseOpti(base(), "ipopt", {
            "print_time": False, "ipopt": IPOPT}), None))
        alts["stagewise_sqpmethod_qpoases"] = ("stage-wise Opti + sqpmethod + qpOASES", lambda p: (StagewiseOpti(
            base(), "sqpmethod", {**QUIET_SQP, "qpsol": "qpoases", "qpsol_options": {
                "printLevel": "none", "error_on_fail": False}}), None))
        alts["stagewise_sqpmethod_hpipm"] = ("stage-wise Opti + sqpmethod + HPIPM", lambda p: (StagewiseOpti(
            base(), "sqpmethod", {**QUIET_SQP, "qpsol": "hpipm", "qpsol_options": {
                "error_on_fail": False, "hpipm": {"mode": "robust"}}}), None))
        alts["stagewise_fatrop"] = ("stage-wise Opti + FATROP", lambda p: (StagewiseOpti(base(), "fatrop", {
            "print_time": False, "structure_detection": "auto", "fatrop": {"print_level": 0}}), None))
    if jit:
        def ours_codegen(p: Problem):
            o = Ours(model)
            return o, codegen(o.opt, jit_flags, workdir)

        def ipopt_jit(p: Problem):
            t0 = time.perf_counter()
            alt = PlainOpti(base(), "ipopt", {"print_time": False, "expand": True, "jit": True, "compiler": "shell",
                                              "jit_options": {"flags": jit_flags, "verbose": False},
                                              "ipopt": IPOPT})
            alt.solve(p)  # Opti builds the NLP solver, and compiles it, at the first solve
            alt.lam = None  # start the sequence like the others
            return alt, time.perf_counter() - t0

        flags = " ".join(jit_flags)
        alts["ours_codegen"] = (f"GN-SQP + ipqp, SX functions in C ({flags})", ours_codegen)
        alts["opti_ipopt_expand_jit"] = (f"Opti + IPOPT, expand + JIT ({flags})", ipopt_jit)
    return alts


# --- measurement ---------------------------------------------------------------------------------
@contextmanager
def quiet_stdout():
    """Solver plugins print banners and debug output straight to fd 1 (qpOASES, OSQP, FATROP):
    send it to /dev/null while they run (every alternative alike)."""
    sys.stdout.flush()
    saved = os.dup(1)
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    try:
        yield
    finally:
        os.dup2(saved, 1)
        os.close(null)
        os.close(saved)


class Checker:
    """One verdict for every alternative's trajectory: the kept optimizer's constraint rows at the
    result (limits, velocity/acceleration, workspace planes, separation rows with exact GJK/EPA
    witnesses), the closest shape pair over all pairs, and the goal error at the last knot."""

    def __init__(self, model) -> None:
        self.opt = opt = TrajectoryOptimizer(model, deployed_config())
        K, F = opt.cfg.knots, opt.cfg.fixed_knots
        self.lo, self.hi = np.tile(opt.lower_a, K - F), np.tile(opt.upper_a, K - F)

    def __call__(self, p: Problem, q: np.ndarray) -> dict:
        opt, F = self.opt, self.opt.cfg.fixed_knots
        qa = q[:, opt.act_index]
        z = qa[F:].ravel()[opt._expand]
        wit, lbg, dmin, pair = opt._witness_vector(z, final=True)
        weights = np.repeat(opt.weights[None], opt.cfg.knots - F, 0).ravel()
        _, _, g, _, cost = opt._eval(z, qa[:F].ravel(), p.goals[F:].ravel(), weights, DT, wit)
        violation, what = opt._violation(z, np.array(g).ravel(), lbg, dmin, pair, self.lo, self.hi)
        exact = opt.collision.witnesses(opt._link_poses(z), exact_below=np.inf).distance.min()
        err = np.linalg.norm(opt.points(q[-1]) - p.goals[-1], axis=1).max()
        return {"violation": violation, "what": what, "dmin": float(exact), "err": float(err), "cost": float(cost)}


def measure(alts: dict, seq: list[Problem], checker: Checker, progress: bool = True) -> dict:
    built, out = {}, {}
    for name, (label, factory) in alts.items():
        t0 = time.perf_counter()
        try:
            with quiet_stdout():
                solver, compile_s = factory(seq[0])
            built[name] = solver
            out[name] = {"label": label, "kind": solver.kind, "build_s": time.perf_counter() - t0,
                         "compile_s": compile_s, "wall": [], "cpu": [], "its": [], "ok": [], "checks": [],
                         "status": []}
        except Exception as exc:  # a plugin that cannot take this problem is a result too
            out[name] = {"label": label, "error": (str(exc).strip().splitlines() or [repr(exc)])[-1][:300]}
    for step, p in enumerate(seq):
        for name, solver in built.items():
            rec = out[name]
            with quiet_stdout():
                t0, c0 = time.perf_counter(), time.thread_time()
                try:
                    res = solver.solve(p)
                except Exception as exc:
                    res = Outcome(p.current.copy(), -1, False, f"raised {(str(exc).splitlines() or [''])[-1][:200]}")
                t1, c1 = time.perf_counter(), time.thread_time()
            if step == 0:
                rec["first_solve_s"] = t1 - t0  # builds the NLP solver (and compiles it, with JIT)
            if step < WARMUP:
                continue
            rec["wall"].append(t1 - t0)
            rec["cpu"].append(c1 - c0)
            rec["its"].append(res.iterations)
            rec["ok"].append(res.ok)
            rec["status"].append(res.status)
            rec["checks"].append(checker(p, res.q) if res.ok else None)
        if progress:
            print(f"\rproblem {step + 1}/{len(seq)}", end="", file=sys.stderr, flush=True)
    if progress:
        print(file=sys.stderr)
    return {name: summarize(rec) for name, rec in out.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--compare", action="store_true", help="also time the other solvers in the installed CasADi")
    parser.add_argument("--jit", action="store_true", help="also time code-generated variants (compiles for minutes)")
    parser.add_argument("--jit-flags", default="-O1", help="compiler flags for --jit (default -O1)")
    parser.add_argument("--steps", type=int, default=STEPS, help=f"problems in the sequence (default {STEPS})")
    args = parser.parse_args()
    model = load_robot("workcell")
    load0 = os.getloadavg()
    seq = record_sequence(model, args.steps)
    workdir = Path(tempfile.mkdtemp(prefix="trajopt_bench_"))
    here = Path.cwd()
    os.chdir(workdir)  # the FATROP conic plugin writes debug_fatrop_*.mtx files into the working directory
    try:
        res = measure(alternatives(model, args.compare, args.jit, args.jit_flags.split(), workdir), seq,
                      Checker(model))
    finally:
        os.chdir(here)
        shutil.rmtree(workdir, ignore_errors=True)
    load1 = os.getloadavg()
    ref = res["plain_opti_ipopt"]
    ref_costs = np.array(ref.get("_costs", [np.nan] * ref["solves"]))
    for r in res.values():
        if "p50_ms" in r:
            r["ratio_p50_vs_opti_ipopt"] = ref["p50_ms"] / r["p50_ms"]
            r["ratio_p95_vs_opti_ipopt"] = ref["p95_ms"] / r["p95_ms"]
            rel = np.array(r.get("_costs", [np.nan] * r["solves"])) / ref_costs  # per problem, both accepted
            r["median_cost_vs_opti_ipopt"] = float(np.nanmedian(rel)) if np.isfinite(rel).any() else None
    for r in res.values():
        r.pop("_costs", None)
    opt = Ours(model).opt
    ours = res["ours"]
    ours |= {"mean_sqp_iterations": ours["mean_iterations"], "rejected": ours["failed"]}  # the README's names
    out = {
        "problem": {"robot": "workcell", "joints": len(model.joint_names), "knots": opt.cfg.knots,
                    "fixed_knots": opt.cfg.fixed_knots, "horizon_s": opt.cfg.knots * DT,
                    "max_sqp_iterations": opt.cfg.max_iterations, "qp_solver": opt.cfg.qp_solver,
                    "shape_pairs": len(opt.collision), "contact_slots_per_knot": opt.slots,
                    "qp_rows": len(opt._lbg), "qp_variables": opt.nz, "problems": len(seq), "warmup": WARMUP,
                    "load_avg_1min": load0[0], "load_avg_1min_end": load1[0], "cpu_count": os.cpu_count(),
                    "casadi": ca.__version__, "measured": time.strftime("%Y-%m-%d %H:%M")},
        "ours": ours, "plain_opti_ipopt": ref,
        "speedup_p50": ours["ratio_p50_vs_opti_ipopt"], "speedup_p95": ours["ratio_p95_vs_opti_ipopt"],
        "targets": {"ours_p95_ms_max": 10.0, "speedup_min": 3.0},
    }
    path = Path(".bench/trajopt.json")
    if args.compare or args.jit:
        out["compare"] = {k: v for k, v in res.items() if k not in ("ours", "plain_opti_ipopt")}
        out["compare_problem"] = out["problem"]
    elif path.exists():  # a plain run keeps the last comparison (with the conditions it was measured in)
        old = json.loads(path.read_text())
        for key in ("compare", "compare_problem"):
            if key in old:
                out[key] = old[key]
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    print(table(res, out["problem"]))
    print(f"\nspeedup vs plain: p50 {out['speedup_p50']:.1f}x, p95 {out['speedup_p95']:.1f}x "
          f"(targets: p95 <= 10 ms, >= 3x); load average {load0[0]:.2f} -> {load1[0]:.2f}")


if __name__ == "__main__":
    main()
