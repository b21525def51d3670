"""Plain C from the simplified scalar programs, for use inside native optimizers.

Plain C rather than CasADi: the scalar programs are already simplified straight-line code with
a register plan, so emitting them statement by statement keeps exactly the counted instructions
(CasADi would rebuild and re-simplify its own graph), and the result needs only a C compiler.

One function per program runs a whole batch in one call:
`void NAME(long n, const double *a, const double *b, double *y, double *z)`.
A program's inputs are split into two consecutive segments read from `a` and `b`, its outputs
into two written to `y` and `z`; each segment has a layout:
- "rows": sample s's values contiguous, `a[s * width + k]` (a (n, width) C-order array, the way
  CasADi and numpy users pack a batch);
- "lanes": groups of `LANES` samples, the group's values of scalar k contiguous,
  `z[(s / LANES) * width * LANES + k * LANES + s % LANES]`, padded to whole groups (the layout of
  the linearization data, which only the generated programs read).
The loop runs over groups of `LANES` samples with the registers as GCC/Clang vector-extension
locals (two doubles: one SSE2 register at -O2 on x86-64, no -march flag), so every instruction
is one vector statement; a last, partial group runs on a copy padded with its first sample.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from collections.abc import Sequence

import numpy as np

from .memory import allocate
from .scalar import ScalarProgram

LANES = 2  # one SSE2 register: measured faster than 1 or 4 lanes on the five-frame chain (docs/autolin.md)
_C_OP = {"add": "{} + {}", "sub": "{} - {}", "mul": "{} * {}", "div": "{} / {}", "neg": "-{}"}
_C_LANEWISE = ("sin", "cos", "sqrt")   # libm per lane
Segment = tuple[str, int]              # (layout, width)


def _segments(spec: Sequence[Segment] | None, total: int) -> list[Segment]:
    segs = list(spec) if spec is not None else [("rows", total)]
    if len(segs) == 1:
        segs.append(("rows", 0))
    if len(segs) != 2 or sum(w for _, w in segs) != total or any(k not in ("rows", "lanes") for k, _ in segs):
        raise ValueError(f"two segments of layout 'rows' or 'lanes' covering {total} scalars, got {spec}")
    return segs


def _lit(x: float) -> str:
    s = repr(float(x))
    return {"inf": "INFINITY", "-inf": "-INFINITY", "nan": "NAN"}.get(s, s)


def c_source(prog: ScalarProgram, name: str, ins: Sequence[Segment] | None = None,
             outs: Sequence[Segment] | None = None) -> str:
    """C source of one scalar program (registers become vector locals); `ins` and `outs` give the
    layouts of the two input and two output segments (default: all in one "rows" segment)."""
    if not name.isidentifier():
        raise ValueError(f"not a C identifier: {name!r}")
    si, so = _segments(ins, len(prog.inputs)), _segments(outs, len(prog.outputs))
    reg, n_regs = allocate(prog)
    w = LANES
    lane_list = ", ".join

    def load(ptr: str, seg: Segment, k: int) -> str:
        kind, width = seg
        if kind == "lanes":
            return f"ld({ptr} + {k * w})"
        return "(vd){" + lane_list(f"{ptr}[{j * width + k}]" for j in range(w)) + "}"

    def store(ptr: str, seg: Segment, k: int, r: str) -> list[str]:
        kind, width = seg
        if kind == "lanes":
            return [f"    st({ptr} + {k * w}, {r});"]
        return [f"    {ptr}[{j * width + k}] = {r}[{j}];" for j in range(w)]

    lines = ["#include <math.h>", "#include <string.h>", "",
             f"typedef double vd __attribute__((vector_size({8 * w})));",
             "static inline vd ld(const double *p) { vd v; memcpy(&v, p, sizeof v); return v; }",
             "static inline void st(double *p, vd v) { memcpy(p, &v, sizeof v); }", "",
             f"static void {name}_group(const double *restrict a, const double *restrict b, double *restrict y, "
             "double *restrict z) {"]
    if n_regs:
        lines.append("    vd " + ", ".join(f"r{k}" for k in range(n_regs)) + ";")
    for k, i in enumerate(prog.inputs):
        if i in reg:
            seg, ptr, kk = (si[0], "a", k) if k < si[0][1] else (si[1], "b", k - si[0][1])
            lines.append(f"    r{reg[i]} = {load(ptr, seg, kk)};")
    live = prog.live()
    for i in live:
        n = prog.nodes[i]
        if n.op in ("const", "zero"):
            v = _lit(n.value)
            lines.append(f"    r{reg[i]} = (vd){{" + lane_list([v] * w) + "};")
    for i in live:
        n = prog.nodes[i]
        args = [f"r{reg[a]}" for a in n.args]
        if n.op in _C_OP:
            lines.append(f"    r{reg[i]} = " + _C_OP[n.op].format(*args) + ";")
        elif n.op in _C_LANEWISE:
            lines.append(f"    r{reg[i]} = (vd){{" + lane_list(f"{n.op}({args[0]}[{j}])" for j in range(w)) + "};")
    for k, o in enumerate(prog.outputs):
        seg, ptr, kk = (so[0], "y", k) if k < so[0][1] else (so[1], "z", k - so[0][1])
        lines += store(ptr, seg, kk, f"r{reg[o]}")
    lines += ["}", ""]

    def step(seg: Segment, ptr: str) -> str:
        kind, width = seg
        return f"{ptr} += {width * w};"

    # the full groups, then the last partial group through padded copies
    rows_in = [(p, s) for p, s in zip("ab", si, strict=True) if s[0] == "rows"]
    rows_out = [(p, s) for p, s in zip("yz", so, strict=True) if s[0] == "rows"]
    lines += [f"void {name}(long n, const double *a, const double *b, double *y, double *z) {{",
              f"    long full = n / {w}, rest = n % {w};",
              "    for (long g = 0; g < full; ++g) {",
              f"        {name}_group(a, b, y, z);",
              "        " + " ".join(step(s, p) for p, s in zip("abyz", si + so, strict=True)),
              "    }",
              "    if (rest) {"]
    for p, (_, width) in rows_in + rows_out:
        lines.append(f"        double t{p}[{max(width * w, 1)}];")
    for p, (_, width) in rows_in:
        lines.append(f"        for (long j = 0; j < {w}; ++j) memcpy(t{p} + j * {width}, {p} + (j < rest ? j : 0) * "
                     f"{width}, {width} * sizeof(double));")
    call = [f"t{p}" if any(p == q for q, _ in rows_in + rows_out) else p for p in "abyz"]
    lines.append(f"        {name}_group({', '.join(call)});")
    for p, (_, width) in rows_out:
        lines.append(f"        memcpy({p}, t{p}, rest * {width} * sizeof(double));")
    lines += ["    }", "}", ""]
    return "\n".join(lines)


def lane_groups(n: int) -> int:
    """Groups of `LANES` samples that hold a batch of n."""
    return -(-n // LANES)


def to_lanes(cols: np.ndarray) -> np.ndarray:
    """(width, n) component arrays -> the "lanes" layout, (groups, width, LANES), padded with the
    first sample."""
    width, n = cols.shape
    g = lane_groups(n)
    pad = np.empty((width, g * LANES))
    pad[:, :n] = cols
    pad[:, n:] = cols[:, :1] if n else 0.0
    return np.ascontiguousarray(pad.reshape(width, g, LANES).transpose(1, 0, 2))


def from_lanes(x: np.ndarray, n: int) -> np.ndarray:
    """The "lanes" layout back to (width, n) component arrays."""
    g, width, lanes = x.shape
    return x.transpose(1, 0, 2).reshape(width, g * lanes)[:, :n]


class CProgram:
    """A scalar program compiled with the system C compiler at -O2 and called through ctypes,
    one call per batch."""

    def __init__(self, prog: ScalarProgram, name: str = "autolin_program", cc: str | None = None,
                 ins: Sequence[Segment] | None = None, outs: Sequence[Segment] | None = None) -> None:
        self.ins, self.outs = _segments(ins, len(prog.inputs)), _segments(outs, len(prog.outputs))
        self.source = c_source(prog, name, self.ins, self.outs)
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
        self._fn.argtypes = [ctypes.c_long] + [ctypes.c_void_p] * 4

    def _shape(self, seg: Segment, n: int) -> tuple[int, ...]:
        kind, width = seg
        return (n, width) if kind == "rows" else (lane_groups(n), width, LANES)

    def run(self, n: int, a: np.ndarray, b: np.ndarray | None = None,
            out: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One call on a batch of n: `a` and `b` C-contiguous float64 arrays in the input
        segments' layouts; returns the two output segments, written into `out` when given (a
        caller that runs a program repeatedly, e.g. inside CG, reuses its buffers: a fresh large
        array is fresh pages from the allocator, which can cost as much as the program)."""
        checks = [(a, self.ins[0]), (b, self.ins[1])]
        checks += list(zip(out, self.outs, strict=True)) if out else []
        for x, seg in checks:
            if seg[1] and (x is None or x.shape != self._shape(seg, n) or x.dtype != np.float64
                           or not x.flags.c_contiguous):
                raise ValueError(f"segment {seg} of a batch of {n} needs a C-contiguous float64 array of shape "
                                 f"{self._shape(seg, n)}, got {None if x is None else (x.shape, x.dtype)}")
        y, z = out or (np.empty(self._shape(self.outs[0], n)), np.empty(self._shape(self.outs[1], n)))
        self._fn(n, a.ctypes.data if self.ins[0][1] else None, b.ctypes.data if self.ins[1][1] else None,
                 y.ctypes.data, z.ctypes.data)
        return y, z

    def __call__(self, inputs: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Per-scalar arrays over a 1-D batch (broadcast as needed) in, per-scalar arrays out:
        packs them into the segments' layouts and unpacks the results (copies)."""
        if len(inputs) != self.n_in:
            raise ValueError(f"expected {self.n_in} input arrays, got {len(inputs)}")
        batch = np.broadcast_shapes(*[np.shape(x) for x in inputs]) if inputs else (1,)
        if len(batch) != 1:
            raise ValueError(f"a 1-D batch is needed, got shape {batch}")
        n = batch[0]
        cols = np.empty((self.n_in, n))
        for k, x in enumerate(inputs):
            cols[k] = x
        w0 = self.ins[0][1]
        segs = [cols[:w0], cols[w0:]]
        packed = [to_lanes(c) if s[0] == "lanes" else np.ascontiguousarray(c.T) for c, s in zip(segs, self.ins,
                                                                                                  strict=True)]
        y, z = self.run(n, *packed)
        out = [from_lanes(x, n) if s[0] == "lanes" else x.T for x, s in zip((y, z), self.outs, strict=True)]
        return list(np.concatenate(out, axis=0))
