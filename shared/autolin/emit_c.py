"""Plain C from the simplified scalar programs, for use inside native optimizers.

Plain C rather than CasADi: the scalar programs are already simplified straight-line code with
a register plan, so emitting them statement by statement keeps exactly the counted instructions
(CasADi would rebuild and re-simplify its own graph), and the result needs only a C compiler.
One function per program loops over the batch:
`void NAME(long n, const double *const *in, const long *stride, double *const *out)`,
in[k][b * stride[k]] the k-th input scalar of sample b (so column views of (B, 3) arrays and
broadcast constants are read in place), out[k][b] the k-th output.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from collections.abc import Sequence
from typing import Any

import numpy as np

from .memory import allocate
from .scalar import ScalarProgram

_C_OP = {"add": "{} + {}", "sub": "{} - {}", "mul": "{} * {}", "div": "{} / {}", "neg": "-{}",
         "sin": "sin({})", "cos": "cos({})", "sqrt": "sqrt({})"}


def c_source(prog: ScalarProgram, name: str) -> str:
    """C source of one scalar program; registers become local variables."""
    if not name.isidentifier():
        raise ValueError(f"not a C identifier: {name!r}")
    reg, n_regs = allocate(prog)
    lines = ["#include <math.h>", "",
             f"void {name}(long n, const double *const *in, const long *stride, double *const *out) {{",
             "    for (long b = 0; b < n; ++b) {"]
    if n_regs:
        lines.append("        double " + ", ".join(f"r{k}" for k in range(n_regs)) + ";")
    for k, i in enumerate(prog.inputs):
        if i in reg:
            lines.append(f"        r{reg[i]} = in[{k}][b * stride[{k}]];")
    live = prog.live()
    for i in live:
        n = prog.nodes[i]
        if n.op in ("const", "zero"):
            lines.append(f"        r{reg[i]} = {float(n.value)!r};")
    for i in live:
        n = prog.nodes[i]
        if n.op in _C_OP:
            lines.append(f"        r{reg[i]} = " + _C_OP[n.op].format(*[f"r{reg[a]}" for a in n.args]) + ";")
    for k, o in enumerate(prog.outputs):
        lines.append(f"        out[{k}][b] = r{reg[o]};")
    lines += ["    }", "}", ""]
    return "\n".join(lines).replace("inf;", "INFINITY;").replace("nan;", "NAN;")


class CProgram:
    """A scalar program compiled with the system C compiler and called through ctypes."""

    def __init__(self, prog: ScalarProgram, name: str = "autolin_program", cc: str | None = None) -> None:
        self.source = c_source(prog, name)
        self.n_in, self.n_out = len(prog.inputs), len(prog.outputs)
        compiler = cc or os.environ.get("CC") or shutil.which("cc")
        if compiler is None:
            raise RuntimeError("no C compiler found (set CC)")
        digest = hashlib.sha1(self.source.encode()).hexdigest()[:16]
        with tempfile.TemporaryDirectory(prefix="autolin_c_") as d:  # the loaded library outlives its file
            src, lib = os.path.join(d, f"{digest}.c"), os.path.join(d, f"{digest}.so")
            with open(src, "w") as fh:
                fh.write(self.source)
            r = subprocess.run([compiler, "-O2", "-shared", "-fPIC", "-o", lib, src, "-lm"], capture_output=True,
                               text=True, check=False)
            if r.returncode != 0:
                raise RuntimeError(f"C compilation failed: {r.stderr.strip()}")
            self._lib = ctypes.CDLL(lib)
        self._fn = getattr(self._lib, name)
        self._fn.restype = None
        self._pp = ctypes.POINTER(ctypes.c_void_p)
        self._pl = ctypes.POINTER(ctypes.c_long)
        self._fn.argtypes = [ctypes.c_long, self._pp, self._pl, self._pp]

    def __call__(self, inputs: Sequence[np.ndarray]) -> list[np.ndarray]:
        if len(inputs) != self.n_in:
            raise ValueError(f"expected {self.n_in} input arrays, got {len(inputs)}")
        batch = np.broadcast_shapes(*[np.shape(x) for x in inputs]) if inputs else ()
        n = int(np.prod(batch))
        # a 1-D batch is read in place through each input's stride (column views of (B, 3) arrays and
        # broadcast constants need no copy); other inputs are copied to contiguous arrays
        ins = [x if _strided(x, batch) else np.ascontiguousarray(np.broadcast_to(x, batch), dtype=np.float64).ravel()
               for x in inputs]
        # the outputs are the rows of one block, so their addresses are a stride apart: no per-array calls
        outs = np.empty((self.n_out, n))
        pin = np.array([x.__array_interface__["data"][0] for x in ins] or [0], dtype=np.uintp)
        strides = np.array([x.strides[0] // 8 if x.ndim else 0 for x in ins] or [0], dtype=np.int64)
        pout = outs.__array_interface__["data"][0] + 8 * n * np.arange(max(self.n_out, 1), dtype=np.uintp)
        self._fn(n, pin.ctypes.data_as(self._pp), strides.ctypes.data_as(self._pl), pout.ctypes.data_as(self._pp))
        return list(outs.reshape((self.n_out,) + batch))


def _strided(x: Any, batch: tuple[int, ...]) -> bool:
    """An array the C function reads as it is: float64 over a 1-D batch (any stride, 0 included)."""
    return (isinstance(x, np.ndarray) and x.dtype == np.float64 and len(batch) == 1 and x.shape == batch
            and x.strides[0] % 8 == 0)
