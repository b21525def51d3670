"""autolin (thesis chapter 3): instruction and memory-operation counts of the generated
rotation programs, counted from the simplified scalar programs themselves, against a
scalar-AD baseline (the framework's own scalar tracing of the same functions, forward and
reverse mode, simplified the same way), and the thesis's figures: forward 33 / reverse 30
for quaternion chaining against 60 / 56 (quaternion) and 99 / 90 (matrix); 13 memory
operations against 20 / 45.

Speed, medians of process CPU time interleaved in one run, one thread each, ratios against
references timed in the same run:
- the five-frame chain (q, t, joint angle per frame), batch 1024: J v and J^T v through the
  generated programs (numpy register plan and plain C; the node-by-node interpreter as an in-run
  baseline) against torch.func's jvp (which evaluates the function again), the pullback of
  torch.func.vjp (recorded once, like the linearization), and CasADi's jtimes (forward and
  reverse mode on SX, mapped over the batch) in its virtual machine and as its generated C;
- the camera calibration's bundle adjustment (bench/_autolin_calibration.py): J v and J^T v of
  its residual over all observations against the same references, and autolin's GN-CG against
  scipy least_squares on calibration/bundle.py's own residuals;
- a small synthetic bundle adjustment: GN-CG against scipy least_squares.
Writes .bench/autolin.json, with the load average at the start and the end.
"""

from __future__ import annotations

import os

# one BLAS / OpenMP thread (set before numpy loads): every entry runs on one thread, so CPU times
# compare like with like (scipy's solver otherwise spends its CPU in idle-spinning BLAS threads)
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere

import shared.autolin as al  # noqa: E402
from shared.autolin import ops as O  # noqa: E402
from shared.autolin import scalar as S  # noqa: E402
from shared.autolin.chain import AXES, CHAIN_TYPES, chain  # noqa: E402

THESIS = {"quat_chain": {"forward": 33, "reverse": 30, "memory_ops": 13},
          "scalar_ad_quat": {"forward": 60, "reverse": 56, "memory_ops": 20},
          "scalar_ad_matrix": {"forward": 99, "reverse": 90, "memory_ops": 45}}
TYPES = CHAIN_TYPES


def summary(p: S.ScalarProgram) -> dict[str, int]:
    c = p.counts()
    return {k: c[k] for k in ("instructions", "muls", "adds", "loads", "stores", "memory_ops",
                              "sin", "cos", "sqrt", "div")}


def chain_components(*x):
    """The same function on scalars, for the scalar-AD baseline (quaternion tangents)."""
    qs = [x[4 * k:4 * k + 4] for k in range(5)]
    ts = [x[20 + 3 * k:23 + 3 * k] for k in range(5)]
    th, p = x[35:40], x[40:43]

    def joint(k):
        h = th[k] * 0.5
        s = S.sin(h)
        return O.qmul(qs[k], (S.cos(h), s * AXES[k][0], s * AXES[k][1], s * AXES[k][2]))

    q, t = joint(0), ts[0]
    for k in range(1, 5):
        t = O.vadd(t, O.qrot(q, ts[k]))
        q = O.qmul(q, joint(k))
    return list(q) + list(O.vadd(t, O.qrot(q, p)))


def counts() -> dict:
    res: dict = {}
    f = al.compile(lambda a, b: a * b, ["quat", "quat"])
    res["quat_chain"] = {"forward": summary(f.scalar["forward"]), "reverse": summary(f.scalar["reverse"]),
                         "linearize": summary(f.scalar["linearize"])}
    r = al.compile(lambda a, b: a @ b, ["rot3", "rot3"])
    res["matrix_chain"] = {"forward": summary(r.scalar["forward"]), "reverse": summary(r.scalar["reverse"])}
    q = S.trace_scalar(lambda *x: O.qmul(x[:4], x[4:]), [f"x{i}" for i in range(8)])
    m = S.trace_scalar(lambda *x: O.matmul(x[:9], x[9:]), [f"x{i}" for i in range(18)])
    for name, p in (("scalar_ad_quat", q), ("scalar_ad_matrix", m)):
        res[name] = {"forward": summary(S.jvp_program(p)), "reverse": summary(S.vjp_program(p))}
    g = al.compile(chain, TYPES)
    c = S.trace_scalar(chain_components, [f"x{i}" for i in range(43)])
    res["five_frames"] = {"autolin": {k: summary(g.scalar[k]) for k in ("linearize", "forward", "reverse")},
                          "scalar_ad": {"forward": summary(S.jvp_program(c)), "reverse": summary(S.vjp_program(c))}}
    return res


def medians_ms(fns: dict, reps: int) -> dict:
    """Median CPU time of the process for each function, interleaved rep by rep. CPU time rather
    than wall time: on the shared machine a run is preempted often, which inflates long entries'
    wall times far more than short ones' (torch runs with one thread; CasADi's and autolin's C
    run in the calling thread). Wall medians go in "wall_ms"."""
    cpu: dict[str, list[float]] = {k: [] for k in fns}
    wall: dict[str, list[float]] = {k: [] for k in fns}
    for fn in fns.values():
        fn()  # warm-up
    for _ in range(reps):
        for k, fn in fns.items():
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            cpu[k].append(time.process_time() - c0)
            wall[k].append(time.perf_counter() - t0)
    out: dict = {k: float(np.median(v) * 1e3) for k, v in cpu.items()}
    out["wall_ms"] = {k: float(np.median(v) * 1e3) for k, v in wall.items()}
    return out


def chain_batch(batch: int) -> tuple:
    rng = np.random.default_rng(0)
    xs = []
    for t in TYPES:
        if t == "quat":
            v = rng.normal(size=(batch, 4))
            xs.append(v / np.linalg.norm(v, axis=1, keepdims=True))
        else:
            xs.append(rng.normal(size=(batch, 3) if t == "vec3" else (batch,)))
    ds = [rng.normal(size=(batch,) if t == "scalar" else (batch, 3)) for t in TYPES]
    w = [rng.normal(size=(batch, 3)), rng.normal(size=(batch, 3))]
    return xs, ds, w


def autolin_fns(batch: int) -> dict:
    """J v and J^T v of the five-frame chain: register plan (numpy), C on packed rows (inputs
    packed beforehand, as CasADi's are; output buffers reused, as inside CG), C on typed arrays
    (packing and unpacking in the call), and the node-by-node interpreter as the in-run baseline."""
    xs, ds, w = chain_batch(batch)
    f = al.compile(chain, TYPES)
    c = f.with_c()
    _, L = f.linearize(*xs)
    _, Lc = c.linearize(*xs)
    D = np.concatenate([d.reshape(batch, -1) for d in ds], axis=1)
    W = np.concatenate(w, axis=1)
    interp = al.Linearized(f.source, f.block, f.scalar, f.data_sizes)
    interp.exe = {k: (lambda ins, p=p: S.replay(p, ins)) for k, p in f.scalar.items()}
    oj, ot = np.empty((batch, c.widths["grad_out"])), np.empty((batch, c.widths["grad_in"]))  # reused, as in CG
    return {"autolin_linearize_ms": lambda: f.linearize(*xs), "autolin_jv_ms": lambda: f.forward(L, *ds),
            "autolin_jtv_ms": lambda: f.reverse(L, *w), "autolin_c_jv_ms": lambda: c.forward_rows(Lc, D, oj),
            "autolin_c_jtv_ms": lambda: c.reverse_rows(Lc, W, ot), "autolin_c_typed_jv_ms": lambda: c.forward(Lc, *ds),
            "autolin_c_typed_jtv_ms": lambda: c.reverse(Lc, *w), "interpreted_jv_ms": lambda: interp.forward(L, *ds),
            "interpreted_jtv_ms": lambda: interp.reverse(L, *w)}


def timings(batch: int, reps: int, with_torch: bool, with_casadi: bool) -> dict:
    fns = autolin_fns(batch)
    if with_torch:
        fns.update(torch_fns(batch))
    if with_casadi:
        fns.update(casadi_fns(batch))
    out = {"batch": batch, "reps": reps, **medians_ms(fns, reps)}
    out["plan_vs_interpreted_jtv"] = out["interpreted_jtv_ms"] / out["autolin_jtv_ms"]
    out["c_vs_plan_jtv"] = out["autolin_jtv_ms"] / out["autolin_c_jtv_ms"]
    out.update(ratios(out))
    return out


REFERENCES = {"jv": ("torch_jvp_ms", "casadi_vm_jv_ms", "casadi_c_jv_ms"),
              "jtv": ("torch_vjp_ms", "casadi_vm_jtv_ms", "casadi_c_jtv_ms")}


def ratios(t: dict) -> dict:
    """reference time / autolin time for each reference and each way of running autolin."""
    out = {}
    for k, refs in REFERENCES.items():
        for ref in refs:
            for mine in (f"autolin_{k}_ms", f"autolin_c_{k}_ms"):
                if ref in t and mine in t:
                    out[f"{ref[:-3]}_over_{mine[:-3]}"] = t[ref] / t[mine]
    return out


def casadi_fns(batch: int) -> dict:
    """The chain in CasADi SX, J v and J^T w by jtimes, mapped over the batch: its virtual machine
    and its generated C (compiled at -O2, as emit_c compiles autolin's programs)."""
    from shared.autolin import casadi_reference as CR  # optional: only the timing comparison needs CasADi

    xs, ds, w = chain_batch(batch)
    jv, jtv = CR.products(*CR.chain_expr(AXES), "chain")
    X = CR.columns(xs)
    D = CR.columns([np.concatenate([d, np.zeros((batch, 1))], 1) if t == "quat" else d
                    for d, t in zip(ds, TYPES, strict=True)])
    W = CR.columns([np.concatenate([w[0], np.zeros((batch, 1))], 1), w[1]])
    out = {}
    for mode in ("vm", "c"):
        fj, fr = CR.batched(jv, batch, mode), CR.batched(jtv, batch, mode)
        out[f"casadi_{mode}_jv_ms"] = lambda fj=fj: fj(X, D)
        out[f"casadi_{mode}_jtv_ms"] = lambda fr=fr: fr(X, W)
    return out


def torch_fns(batch: int) -> dict:
    import torch  # optional heavy dependency, only for the timing comparison
    from torch.func import jvp, vjp

    from shared.autolin.torch_reference import five_frame_chain

    torch.set_num_threads(1)
    xs, ds, w = chain_batch(batch)

    ref = five_frame_chain(AXES)

    tx = tuple(torch.tensor(x) for x in xs)
    td = tuple(torch.tensor(np.concatenate([d, np.zeros((batch, 1))], 1)) if t == "quat" else torch.tensor(d)
               for d, t in zip(ds, TYPES, strict=True))
    _, pull = vjp(ref, *tx)
    tw = (torch.tensor(np.concatenate([w[0], np.zeros((batch, 1))], 1)), torch.tensor(w[1]))
    return {"torch_jvp_ms": lambda: jvp(ref, tx, td), "torch_vjp_ms": lambda: pull(tw)}


def bundle(reps: int) -> dict:
    """GN-CG against scipy least_squares (trf, finite-difference Jacobian) on the same residuals:
    wall time to each one's final cost, the traced programs compiled beforehand."""
    from scipy.optimize import least_squares

    from shared.autolin.bundle import make_problem, numpy_residuals, numpy_start, reprojection
    from shared.autolin.solver import LeastSquares

    pr = make_problem(n_cams=4, n_points=25, noise_px=0.5, seed=1)
    t0 = time.perf_counter()
    ls = LeastSquares(reprojection, ["quat", "vec3", "vec3"], ["scalar", "scalar"], [pr.cam, pr.cam, pr.pt])
    compile_s = time.perf_counter() - t0
    fixed = [np.arange(len(pr.quats)) == 0, np.arange(len(pr.trans)) == 0, None]
    out: dict = {}
    t: dict[str, list[float]] = {"autolin_gn_cg_s": [], "scipy_least_squares_s": []}
    for _ in range(reps):
        t0 = time.process_time()
        res = ls.solve([pr.quats, pr.trans, pr.points], [pr.uv[:, 0], pr.uv[:, 1]], fixed=fixed)
        t["autolin_gn_cg_s"].append(time.process_time() - t0)
        t0 = time.process_time()
        ref = least_squares(numpy_residuals, numpy_start(pr), args=(pr,), method="trf", x_scale="jac")
        t["scipy_least_squares_s"].append(time.process_time() - t0)
    out = {k: float(np.median(v)) for k, v in t.items()}
    out.update(observations=int(pr.cam.size), compile_s=compile_s, autolin_cost=res.cost, scipy_cost=float(ref.cost),
               autolin_iterations=res.iterations, autolin_cg_iterations=res.cg_iterations, scipy_nfev=int(ref.nfev))
    out["speedup"] = out["scipy_least_squares_s"] / out["autolin_gn_cg_s"]
    return out


def calibration(args: argparse.Namespace) -> dict:
    """The camera calibration's bundle adjustment: products and solve (bench/_autolin_calibration.py)."""
    import _autolin_calibration as cal  # beside this script; imports the calibration package

    c_mode = emit_c_available()
    fns, batch = cal.product_fns(cal.make_problem(args.calib_frames)[2], not args.no_timing,
                                 not args.no_timing and not args.no_casadi, c_mode)
    out: dict = {"products": {"observations": batch, "reps": args.reps, **medians_ms(fns, args.reps)}}
    out["products"].update(ratios(out["products"]))
    p = out["products"]
    print(f"calibration residual, {batch} observations, median of {args.reps}: J v {p['autolin_jv_ms']:.2f} ms "
          f"(C {p.get('autolin_c_jv_ms', float('nan')):.2f}), J^T v {p['autolin_jtv_ms']:.2f} ms "
          f"(C {p.get('autolin_c_jtv_ms', float('nan')):.2f})")
    for ref in ("torch_jvp_ms", "torch_vjp_ms", "casadi_vm_jv_ms", "casadi_vm_jtv_ms", "casadi_c_jv_ms",
                "casadi_c_jtv_ms"):
        if ref in p:
            mine = "autolin_c" if "_c_" in ref else "autolin"
            k = "jv" if ref.endswith(("jv_ms", "jvp_ms")) else "jtv"
            print(f"  {ref[:-3]} {p[ref]:.2f} ms: {p[f'{ref[:-3]}_over_{mine}_{k}']:.2f}x")
    s = cal.solve(args.calib_frames, 3, c_mode, args.dense)
    out["solve"] = s
    sec, wall, cost = s["cpu_seconds"], s["seconds"], s["final_cost"]
    print(f"calibration bundle adjustment, {s['cameras']} cameras, {s['frames']} frame sets, {s['observations']} "
          f"corners, {s['unknowns']} unknowns, median of {s['reps']} (start cost {cost['start']:.6f}):")
    for k in sec:
        extra = s.get(k, {})
        print(f"  {k:20s} {sec[k]:7.2f} s CPU ({wall[k]:.2f} wall)  final cost {cost[k]:.9f}  " + "  ".join(
            f"{a}={b:.3g}" if isinstance(b, float) else f"{a}={b}" for a, b in extra.items()))
    return out


def emit_c_available() -> bool:
    return shutil.which(os.environ.get("CC", "cc")) is not None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--no-timing", action="store_true", help="no torch.func comparison (no torch import)")
    ap.add_argument("--no-bundle", action="store_true", help="skip the bundle-adjustment comparison")
    ap.add_argument("--no-casadi", action="store_true", help="no CasADi comparison")
    ap.add_argument("--no-calibration", action="store_true", help="skip the camera-calibration bundle adjustment")
    ap.add_argument("--calib-frames", type=int, default=120, help="frame sets of the calibration problem")
    ap.add_argument("--dense", action="store_true", help="also scipy least_squares without the sparsity (slow)")
    ap.add_argument("--out", default=".bench/autolin.json")
    args = ap.parse_args()
    res = {"counts": counts(), "thesis": THESIS}
    qc, bq, bm = res["counts"]["quat_chain"], res["counts"]["scalar_ad_quat"], res["counts"]["scalar_ad_matrix"]
    print("quaternion chaining, instructions forward / reverse, memory operations (forward):")
    print(f"  autolin           {qc['forward']['instructions']} / {qc['reverse']['instructions']}, "
          f"{qc['forward']['memory_ops']}   (thesis 33 / 30, 13)")
    print(f"  scalar AD, quat   {bq['forward']['instructions']} / {bq['reverse']['instructions']}, "
          f"{bq['forward']['memory_ops']}   (thesis 60 / 56, 20)")
    print(f"  scalar AD, matrix {bm['forward']['instructions']} / {bm['reverse']['instructions']}, "
          f"{bm['forward']['memory_ops']}   (thesis 99 / 90, 45)")
    mc = res["counts"]["matrix_chain"]
    print(f"  autolin, matrix   {mc['forward']['instructions']} / {mc['reverse']['instructions']}, "
          f"{mc['forward']['memory_ops']}   (rotation matrices with rotation-vector gradients)")
    ff = res["counts"]["five_frames"]
    print(f"five-frame chain, instructions forward / reverse: autolin {ff['autolin']['forward']['instructions']} / "
          f"{ff['autolin']['reverse']['instructions']}, scalar AD {ff['scalar_ad']['forward']['instructions']} / "
          f"{ff['scalar_ad']['reverse']['instructions']}")
    res["match_thesis"] = all(res["counts"][k][d]["instructions"] == v[d] for k, v in THESIS.items()
                              for d in ("forward", "reverse")) and all(
        res["counts"][k]["forward"]["memory_ops"] == v["memory_ops"] for k, v in THESIS.items())
    res["load_average"] = os.getloadavg()
    t = timings(args.batch, args.reps, not args.no_timing, not args.no_timing and not args.no_casadi)
    res["timing"] = t
    print(f"five-frame chain, batch {t['batch']}, median of {t['reps']} (one thread, noisy machine): J v "
          f"{t['autolin_jv_ms']:.2f} ms (C {t['autolin_c_jv_ms']:.2f}), J^T v {t['autolin_jtv_ms']:.2f} ms "
          f"(C {t['autolin_c_jtv_ms']:.2f}); node-by-node interpreter J^T v {t['interpreted_jtv_ms']:.2f} ms")
    if not args.no_timing:
        print(f"  against torch.func: jvp {t['torch_jvp_ms']:.2f} ms ({t['torch_jvp_over_autolin_jv']:.1f}x, C "
              f"{t['torch_jvp_over_autolin_c_jv']:.1f}x), vjp pullback {t['torch_vjp_ms']:.2f} ms "
              f"({t['torch_vjp_over_autolin_jtv']:.1f}x, C {t['torch_vjp_over_autolin_c_jtv']:.1f}x); target >= 2x")
    if "casadi_c_jv_ms" in t:
        print(f"  against CasADi jtimes: virtual machine J v {t['casadi_vm_jv_ms']:.2f} ms "
              f"({t['casadi_vm_jv_over_autolin_jv']:.1f}x), J^T v {t['casadi_vm_jtv_ms']:.2f} ms "
              f"({t['casadi_vm_jtv_over_autolin_jtv']:.1f}x); generated C J v {t['casadi_c_jv_ms']:.2f} ms "
              f"({t['casadi_c_jv_over_autolin_c_jv']:.2f}x of autolin's C), J^T v {t['casadi_c_jtv_ms']:.2f} ms "
              f"({t['casadi_c_jtv_over_autolin_c_jtv']:.2f}x)")
    if not args.no_bundle:
        b = bundle(3)
        res["bundle"] = b
        print(f"bundle adjustment, {b['observations']} observations, median of 3: GN-CG {b['autolin_gn_cg_s']:.2f} s "
              f"(cost {b['autolin_cost']:.6f}) vs scipy least_squares {b['scipy_least_squares_s']:.2f} s "
              f"(cost {b['scipy_cost']:.6f}), {b['speedup']:.1f}x; tracing and generation {b['compile_s']:.2f} s")
    if not args.no_calibration:
        res["calibration"] = calibration(args)
    res["load_average_end"] = os.getloadavg()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
