"""The bench's functions built in CasADi (SX): the five-frame chain and the calibration
residual, with their Jacobian-vector products from `casadi.jtimes` (forward mode for J v,
reverse mode for J^T w), mapped over a batch. Two ways to run them: CasADi's SX virtual machine,
or its C code generation compiled with the system C compiler at -O2 (the flags emit_c uses) and
loaded with `casadi.external`. Only bench/autolin.py and the tests load this module.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

import casadi as ca
import numpy as np

from . import ops as O
from .camera import reprojection_components

CHAIN_SIZES = [4] * 5 + [3] * 5 + [1] * 5 + [3]   # q0..q4, t0..t4, theta0..theta4, p
CAMERA_SIZES = [4, 3, 3, 3, 3, 4, 3, 3, 1, 1]     # q_c t_c (fx fy cx) (cy k1 k2) (p1 p2 k3) q_b t_b obj u v


def _split(x: ca.SX, sizes: Sequence[int]) -> list[tuple]:
    out, k = [], 0
    for n in sizes:
        out.append(tuple(x[k + i] for i in range(n)))
        k += n
    return out


def chain_expr(axes: Sequence[Sequence[float]]) -> tuple[ca.SX, ca.SX]:
    """(inputs, outputs) of the five-frame chain: outputs the orientation (4) and position (3)."""
    x = ca.SX.sym("x", sum(CHAIN_SIZES))
    a = _split(x, CHAIN_SIZES)
    qs, ts, th, p = a[0:5], a[5:10], a[10:15], a[15]

    def joint(k: int) -> tuple:
        h = th[k][0] * 0.5
        s = ca.sin(h)
        return O.qmul(qs[k], (ca.cos(h), s * axes[k][0], s * axes[k][1], s * axes[k][2]))

    q, t = joint(0), ts[0]
    for k in range(1, 5):
        t = O.vadd(t, O.qrot(q, ts[k]))
        q = O.qmul(q, joint(k))
    return x, ca.vertcat(*q, *O.vadd(t, O.qrot(q, p)))


def camera_expr() -> tuple[ca.SX, ca.SX]:
    """(inputs, outputs) of one observation's calibration residual (pixel error, 2)."""
    x = ca.SX.sym("x", sum(CAMERA_SIZES))
    a = _split(x, CAMERA_SIZES)
    return x, ca.vertcat(*reprojection_components(*a[:8], a[8][0], a[9][0]))


def products(x: ca.SX, y: ca.SX, name: str) -> tuple[ca.Function, ca.Function]:
    """(J v, J^T w) as CasADi functions of (x, v) and (x, w)."""
    v = ca.SX.sym("v", x.numel())
    w = ca.SX.sym("w", y.numel())
    return (ca.Function(f"{name}_jv", [x, v], [ca.jtimes(y, x, v)]),
            ca.Function(f"{name}_jtv", [x, w], [ca.jtimes(y, x, w, True)]))


def compiled(fn: ca.Function, cc: str | None = None) -> ca.Function:
    """`fn` through CasADi's C code generation, compiled at -O2 and loaded back."""
    compiler = cc or shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        raise RuntimeError("no C compiler found (cc or gcc) for CasADi's generated code")
    folder = Path(tempfile.mkdtemp(prefix="autolin-casadi-"))
    src = folder / f"{fn.name()}.c"
    fn.generate(src.name, {"with_header": False})
    Path(src.name).replace(src)  # generate() writes into the working directory
    lib = folder / f"{fn.name()}.so"
    r = subprocess.run([compiler, "-O2", "-shared", "-fPIC", "-o", str(lib), str(src), "-lm"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"compiling CasADi's code for {fn.name()} failed: {r.stderr.strip()[:500]}")
    return ca.external(fn.name(), str(lib))


def batched(fn: ca.Function, batch: int, mode: str) -> Callable[..., ca.DM]:
    """fn mapped over `batch` columns; mode "vm" (SX virtual machine) or "c" (generated C)."""
    mapped = fn.map(batch)
    if mode == "c":
        return compiled(mapped)
    if mode != "vm":
        raise ValueError(f"mode must be 'vm' or 'c', got {mode!r}")
    return mapped


def columns(arrays: Sequence[np.ndarray]) -> ca.DM:
    """Per-sample arrays (B,) or (B, n) stacked into CasADi's (n_total, B) column layout."""
    return ca.DM(np.concatenate([np.asarray(a, float).reshape(len(a), -1) for a in arrays], axis=1).T)
