"""bench/autolin.py's camera-calibration part: the bundle adjustment of `xm calibrate`
(calibration/bundle.py's residuals: OpenCV pinhole with 5 distortion coefficients, camera poses,
a board pose per frame set) on detections of the simulated rig: the world model's cameras at
640x480 and the world's calibration sequence of board poses, corners projected with 0.1 px noise
(calibration/synthetic.py), started from the pipeline's own initial guess (calibration/init.py).

Times J v and J^T v of one observation's residual over all observations (autolin's programs, numpy
and C, against torch.func and CasADi), and the solve: autolin's GN-CG against scipy's
least_squares on calibration/bundle.py's own residual function (trf with the Jacobian's sparsity,
the way scipy documents bundle adjustment; and without it, dense), and the calibration's own
Levenberg-Marquardt (finite-difference Jacobian, direct Schur solve) for reference.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix

from calibration.bundle import Problem, levenberg_marquardt, observations
from calibration.cli import true_cameras
from calibration.init import initial_guess
from calibration.synthetic import project_views
from services.world import calibration_sequence as calseq
from shared.autolin import camera as C
from shared.autolin.solver import LeastSquares
from shared.charuco import BoardSpec

SIZE = (640, 480)


def make_problem(frames: int, seed: int = 0, noise_px: float = 0.1) -> tuple[Problem, np.ndarray, C.CameraProblem]:
    """calibration/bundle.py's Problem and start x0, and the same as autolin parameter arrays."""
    board = BoardSpec()
    cams = true_cameras(*SIZE)
    names = list(cams)
    det = project_views(board, names, [SIZE] * len(names), [cams[n][0] for n in names], [np.zeros(5)] * len(names),
                        [cams[n][1] for n in names], calseq.sequence(board, frames, seed), noise_px=noise_px,
                        seed=seed)
    init = initial_guess(det, board)
    obs = observations(det, board, set(init.rig_T_board))
    prob = Problem(len(names), init.reference, obs, "full")
    x0 = prob.pack(init.K, init.dist, init.cam_T_rig, init.rig_T_board)
    ext = np.zeros((prob.n, 6))  # the reference camera's pose is the rig frame
    ext[prob.movable] = x0[prob.o_ext:prob.o_board].reshape(-1, 6)
    cp = C.from_rotation_vectors(prob.intrinsics(x0), ext, x0[prob.o_board:].reshape(-1, 6), prob.ref, obs.cam,
                                 obs.frame, obs.obj, obs.uv)
    return prob, x0, cp


def sparsity(prob: Problem) -> coo_matrix:
    """Which unknowns each residual reads: its camera's intrinsics and pose, its frame set's board."""
    obs, m = prob.obs, len(prob.obs.cam)
    ni = prob.n_intr
    cols = [ni * obs.cam[:, None] + np.arange(ni), prob.o_board + 6 * obs.frame[:, None] + np.arange(6)]
    rows = [np.repeat(np.arange(m), ni), np.repeat(np.arange(m), 6)]
    moving = np.flatnonzero(obs.cam != prob.ref)
    ext = np.array([prob.ext_index.get(c, 0) for c in obs.cam[moving]], int)
    cols.append(prob.o_ext + 6 * ext[:, None] + np.arange(6))
    rows.append(np.repeat(moving, 6))
    r = np.concatenate(rows)
    c = np.concatenate([x.ravel() for x in cols])
    r2 = np.concatenate([2 * r, 2 * r + 1])
    return coo_matrix((np.ones(len(r2)), (r2, np.concatenate([c, c]))), shape=(2 * m, prob.size))


def product_fns(cp: C.CameraProblem, with_torch: bool, with_casadi: bool, c_mode: bool) -> tuple[dict, int]:
    """J v and J^T v of the residual over all observations, each way."""
    ls = LeastSquares(C.reprojection, C.PARAM_TYPES, C.DATA_TYPES, cp.index)
    xs = ls._gather(cp.params, cp.data)
    batch = len(cp.index[0])
    rng = np.random.default_rng(0)
    grad = [rng.normal(size=(batch,) + (() if t == "scalar" else (3,))) for t in ls.f.in_types]
    w = [rng.normal(size=batch), rng.normal(size=batch)]
    _, L = ls.f.linearize(*xs)
    fns = {"autolin_jv_ms": lambda: ls.f.forward(L, *grad), "autolin_jtv_ms": lambda: ls.f.reverse(L, *w)}
    if c_mode:
        fc = ls.f.with_c()
        _, Lc = fc.linearize(*xs)
        G = np.concatenate([g.reshape(batch, -1) for g in grad], axis=1)
        Wr = np.stack(w, axis=1)  # packed beforehand, as CasADi's inputs are
        oj, ot = np.empty((batch, fc.widths["grad_out"])), np.empty((batch, fc.widths["grad_in"]))  # reused, as in CG
        fns.update(autolin_c_jv_ms=lambda: fc.forward_rows(Lc, G, oj),
                   autolin_c_jtv_ms=lambda: fc.reverse_rows(Lc, Wr, ot),
                   autolin_c_typed_jv_ms=lambda: fc.forward(Lc, *grad),
                   autolin_c_typed_jtv_ms=lambda: fc.reverse(Lc, *w))
    # the references take quaternion tangents: the rotation vectors padded with a zero
    tangents = [np.concatenate([g, np.zeros((batch, 1))], 1) if t == "quat" else g
                for g, t in zip(grad, ls.f.in_types, strict=True)]
    if with_torch:
        import torch  # optional heavy dependency, only for the timing comparison
        from torch.func import jvp, vjp

        def residual(*a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            return C.reprojection_components(*[x.unbind(-1) for x in a[:8]], a[8], a[9])

        tx = tuple(torch.tensor(x) for x in xs)
        td = tuple(torch.tensor(x) for x in tangents)
        _, pull = vjp(residual, *tx)
        tw = tuple(torch.tensor(x) for x in w)
        fns.update(torch_jvp_ms=lambda: jvp(residual, tx, td), torch_vjp_ms=lambda: pull(tw))
    if with_casadi:
        from shared.autolin import casadi_reference as CR  # optional: only the bench compares with CasADi

        jv, jtv = CR.products(*CR.camera_expr(), "camera")
        X, D, W = CR.columns(xs), CR.columns(tangents), CR.columns(w)
        for mode in ("vm", "c") if c_mode else ("vm",):
            fj, fr = CR.batched(jv, batch, mode), CR.batched(jtv, batch, mode)
            fns[f"casadi_{mode}_jv_ms"] = lambda fj=fj: fj(X, D)
            fns[f"casadi_{mode}_jtv_ms"] = lambda fr=fr: fr(X, W)
    return fns, batch


def solve(frames: int, reps: int, c_mode: bool, dense: bool) -> dict:
    """CPU and wall time of each solver to its final cost, and the time autolin's GN-CG takes to
    first reach each reference's final cost (from the costs it records after each step); the
    speedups are in CPU time (the shared machine's preemption inflates wall times)."""
    prob, x0, cp = make_problem(frames)
    mask = np.ones(len(prob.obs.cam), bool)
    t0 = time.perf_counter()
    ls = LeastSquares(C.reprojection, C.PARAM_TYPES, C.DATA_TYPES, cp.index, backend="c" if c_mode else "numpy")
    compile_s = time.perf_counter() - t0
    sp = sparsity(prob)

    def fun(x: np.ndarray) -> np.ndarray:
        return prob.residuals(x, mask)

    runs: dict = {"gn_cg_schur_jacobi": [], "gn_cg_schur": [], "scipy_sparse": [], "calibration_lm": []}
    cpu: dict = {k: [] for k in runs}
    results: dict = {}

    def timed(key: str, fn: Callable[[], Any]) -> Any:
        t0, c0 = time.perf_counter(), time.process_time()
        r = fn()
        runs.setdefault(key, []).append(time.perf_counter() - t0)
        cpu.setdefault(key, []).append(time.process_time() - c0)
        return r

    xl = x0
    for _ in range(reps):
        for pc, key in (("schur-jacobi", "gn_cg_schur_jacobi"), ("schur", "gn_cg_schur")):
            results[key] = timed(key, lambda pc=pc: ls.solve(cp.params, cp.data, fixed=cp.fixed, preconditioner=pc))
        results["scipy_sparse"] = timed("scipy_sparse", lambda: least_squares(fun, x0, jac_sparsity=sp, method="trf",
                                                                            x_scale="jac"))
        # soft-L1 with a huge scale: plain least squares
        xl, _ = timed("calibration_lm", lambda: levenberg_marquardt(prob, x0, mask, 1e6))
    if dense:  # minutes at the default size: once
        results["scipy_dense"] = timed("scipy_dense", lambda: least_squares(fun, x0, method="trf", x_scale="jac"))
    out: dict = {"frames": frames, "observations": int(len(prob.obs.cam)), "unknowns": int(prob.size),
                 "cameras": int(prob.n), "reps": reps, "backend": "c" if c_mode else "numpy", "compile_s": compile_s}
    out["seconds"] = {k: float(np.median(v)) for k, v in runs.items()}
    out["cpu_seconds"] = {k: float(np.median(v)) for k, v in cpu.items()}
    costs = {k: float(results[k].cost) for k in results}
    costs["calibration_lm"] = float(0.5 * np.sum(fun(xl) ** 2))
    costs["start"] = float(0.5 * np.sum(fun(x0) ** 2))
    out["final_cost"] = costs
    for key in ("gn_cg_schur_jacobi", "gn_cg_schur"):
        r = results[key]
        out[key] = {"iterations": r.iterations, "cg_iterations": r.cg_iterations}
        for ref in ("scipy_sparse", "scipy_dense", "calibration_lm"):
            if ref not in costs:
                continue
            # the first recorded cost at or below the reference's final cost, in CPU and wall seconds
            reach = [(c, w) for k, c, w in zip(r.costs, r.cpu_times, r.times, strict=True)
                     if k <= costs[ref] * (1 + 1e-12)]
            out[key][f"reaches_{ref}_cpu_s"] = reach[0][0] if reach else None
            out[key][f"reaches_{ref}_s"] = reach[0][1] if reach else None
            if reach:
                out[key][f"speedup_vs_{ref}"] = out["cpu_seconds"][ref] / reach[0][0]
    out["autolin_matches_residuals"] = bool(np.allclose(
        np.stack(ls.residuals(cp.params, cp.data)[0], 1).ravel(), fun(x0), atol=1e-9))
    return out
