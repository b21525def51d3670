"""The four generated programs (thesis sections 3.2.1-3.2.4), their lowering to simplified
scalar programs, and batched execution with numpy.

`compile(fn, types)` traces `fn` once and returns a `Linearized` with
`linearize` (values and linearization data), `forward` (J v), `reverse` (J^T w) and
`accumulate` (x (+) dx per type). Forward and reverse use only the stored data.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import ops as O
from . import scalar as S
from .emit_c import CProgram, from_lanes, to_lanes
from .memory import Executable
from .trace import Instr, Program, trace

counters = O.counters


class NonFiniteError(FloatingPointError):
    """A linearization produced NaN or Inf; the message names the instruction and line."""


def _zero_var(p: Program, typ: str) -> int:
    v = p.var(typ)
    p.consts[v] = (0.0,) * O.SIZE[typ]
    return v


def linearization_program(src: Program) -> tuple[Program, list[int]]:
    """Each instruction, then its linearizer on its arguments and result (3.2.1). Returns the
    program and its data variables, one per source instruction, in order."""
    p = Program("linearize", list(src.types), dict(src.consts), [], list(src.inputs), list(src.outputs))
    data = []
    for ins in src.instrs:
        p.instrs.append(ins)
        d = p.var("data")
        p.instrs.append(Instr(ins.op + ".lin", ins.args + ins.outs, (d,), ins.line))
        data.append(d)
    p.outputs = list(src.outputs) + data
    return p, data


def forward_program(src: Program) -> Program:
    """Each operator replaced by its forward rule on input gradients and its data (3.2.2)."""
    p = Program("forward")
    data = [p.var("data") for _ in src.instrs]
    g: dict[int, int] = {}
    for v in src.inputs:
        g[v] = p.var(O.GRAD[src.types[v]])
    p.inputs = data + [g[v] for v in src.inputs]
    for k, ins in enumerate(src.instrs):
        args = [g[a] if a in g else _zero_var(p, O.GRAD[src.types[a]]) for a in ins.args]
        o = p.var(O.GRAD[src.types[ins.outs[0]]])
        p.instrs.append(Instr(ins.op + ".fwd", (data[k], *args), (o,), ins.line))
        g[ins.outs[0]] = o
    p.outputs = [g[v] if v in g else _zero_var(p, O.GRAD[src.types[v]]) for v in src.outputs]
    return p


def _merge(p: Program, typ: str, parts: list[int], line: str) -> int:
    """Binary tree of additions over the gradients of a variable read more than once."""
    while len(parts) > 1:
        nxt = []
        for k in range(0, len(parts) - 1, 2):
            o = p.var(typ)
            p.instrs.append(Instr(f"add.{typ}.fwd", (-1, parts[k], parts[k + 1]), (o,), line))
            nxt.append(o)
        if len(parts) % 2:
            nxt.append(parts[-1])
        parts = nxt
    return parts[0]


def reverse_program(src: Program) -> Program:
    """Instructions in reverse order, each replaced by its reverse rule on the output gradient
    and its data (3.2.3); reads of a variable more than once are merged in a binary tree."""
    p = Program("reverse")
    data = [p.var("data") for _ in src.instrs]
    contrib: dict[int, list[int]] = {}
    gout = []
    for v in src.outputs:
        w = p.var(O.GRAD[src.types[v]])
        gout.append(w)
        contrib.setdefault(v, []).append(w)
    p.inputs = data + gout
    for k in range(len(src.instrs) - 1, -1, -1):
        ins = src.instrs[k]
        o = ins.outs[0]
        if o not in contrib:
            continue  # the result reaches no output: no gradient flows back
        go = _merge(p, O.GRAD[src.types[o]], contrib.pop(o), ins.line)
        outs = tuple(p.var(O.GRAD[src.types[a]]) for a in ins.args)
        p.instrs.append(Instr(ins.op + ".rev", (data[k], go), outs, ins.line))
        for a, w in zip(ins.args, outs, strict=False):
            if a not in src.consts:
                contrib.setdefault(a, []).append(w)
    p.outputs = [_merge(p, O.GRAD[src.types[v]], contrib[v], "") if v in contrib
                 else _zero_var(p, O.GRAD[src.types[v]]) for v in src.inputs]
    return p


def accumulation_program(src: Program) -> Program:
    """x (+) dx for each argument, with the addition of its value and gradient types (3.2.4)."""
    p = Program("accumulate")
    xs = [p.var(src.types[v]) for v in src.inputs]
    gs = [p.var(O.GRAD[src.types[v]]) for v in src.inputs]
    p.inputs = xs + gs
    for x, gv, v in zip(xs, gs, src.inputs, strict=False):
        o = p.var(src.types[v])
        p.instrs.append(Instr(f"acc.{src.types[v]}", (x, gv), (o,)))
        p.outputs.append(o)
    return p


# --- lowering to scalar programs -----------------------------------------------------------
def lower(p: Program, data_sizes: list[int] | None = None, data_consts: dict[int, float] | None = None,
          data_alias: dict[int, int] | None = None) -> tuple[S.ScalarProgram, list[int]]:
    """Runs the block program on `Sym` components: a simplified scalar program. Data variables
    take their sizes from `data_sizes` (as the linearization program produced them); by
    position among all data scalars, those in `data_consts` are constants, folded into the
    program instead of read, and those in `data_alias` read the earlier data scalar they equal.
    Nodes remember the block instruction they came from (`origin`). Returns the program and the
    sizes of the data variables it produced or consumed."""
    b = S.Builder(simplify=True)
    env: dict[int, tuple[Any, ...]] = {}
    sizes = list(data_sizes or [])
    consts, alias = data_consts or {}, data_alias or {}
    flat: dict[int, Any] = {}
    di = 0
    for v in p.inputs:
        if p.types[v] == "data":
            n = sizes[di]
            di += 1
            comps = []
            for c in range(n):
                j = len(flat)
                flat[j] = (b.const(consts[j]) if j in consts else flat[alias[j]] if j in alias
                           else b.input(f"v{v}_{c}"))
                comps.append(flat[j])
            env[v] = tuple(comps)
            continue
        n = O.SIZE[p.types[v]]
        env[v] = tuple(b.input(f"v{v}_{c}") for c in range(n))
    for v, c in p.consts.items():
        env[v] = tuple(b.const(x) for x in c)
    produced = []
    for k, ins in enumerate(p.instrs):
        b.origin = k
        base, _, kind = ins.op.rpartition(".")
        if ins.op.startswith("acc."):
            res = (O.accumulate(ins.op[4:], *[env[a] for a in ins.args]),)
        elif kind == "lin":
            op = O.rules(base)
            n_in = len(op.arg_types)
            res = (tuple(op.lin(*[env[a] for a in ins.args[:n_in]], env[ins.args[n_in]])),)
            produced.append(len(res[0]))
        elif kind == "fwd":
            op = O.rules(base)
            res = (op.fwd(env.get(ins.args[0], ()), *[env[a] for a in ins.args[1:]]),)
        elif kind == "rev":
            res = O.rules(base).rev(env[ins.args[0]], env[ins.args[1]])
        else:
            res = (O.OPS[ins.op].eval(*[env[a] for a in ins.args]),)
        for o, r in zip(ins.outs, res, strict=False):
            env[o] = tuple(x if isinstance(x, S.Sym) else b.const(x) for x in r)
    b.prog.outputs = [x.i for v in p.outputs for x in env[v]]
    return S.prune(b.prog), produced or sizes


# --- execution ----------------------------------------------------------------------------
def _comps(x: Any, typ: str) -> list[np.ndarray]:
    a = np.asarray(x, dtype=float)
    n = O.SIZE[typ]
    if typ == "scalar":
        return [a]
    if typ in ("mat3", "rot3"):
        if a.shape[-2:] != (3, 3):
            raise ValueError(f"a mat3 needs trailing shape (3, 3), got {a.shape}")
        a = a.reshape(a.shape[:-2] + (9,))
    if a.shape[-1:] != (n,):
        raise ValueError(f"a {typ} needs trailing size {n}, got shape {a.shape}")
    return [a[..., c] for c in range(n)]


def _pack(comps: list[Any], typ: str, batch: tuple[int, ...]) -> np.ndarray:
    cs = [np.broadcast_to(np.asarray(c, dtype=float), batch) for c in comps]
    if typ == "scalar":
        return np.array(cs[0])
    a = np.stack(cs, axis=-1)
    return a.reshape(batch + (3, 3)) if typ in ("mat3", "rot3") else a


@dataclass
class Linearized:
    """A traced function and its four generated, simplified programs."""

    source: Program
    block: dict[str, Program]
    scalar: dict[str, S.ScalarProgram]
    data_sizes: list[int] = field(default_factory=list)
    exe: dict[str, Callable[[Sequence[Any]], list[Any]]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.exe = {k: Executable(p) for k, p in self.scalar.items()}

    def with_c(self) -> CLinearized:
        """The same programs compiled to plain C (`emit_c`), one call per batch."""
        return CLinearized(self.source, self.block, self.scalar, self.data_sizes)

    @property
    def in_types(self) -> list[str]:
        return [self.source.types[v] for v in self.source.inputs]

    @property
    def out_types(self) -> list[str]:
        return [self.source.types[v] for v in self.source.outputs]

    def _run(self, name: str, flat: list[Any], batch: tuple[int, ...],
             on_node: Callable[[int, Any], None] | None = None) -> list[Any]:
        xs = [x if np.shape(x) == batch else np.broadcast_to(x, batch) for x in flat]
        if on_node is not None:
            return S.replay(self.scalar[name], xs, on_node)
        return self.exe[name](xs)

    def linearize(self, *xs: Any) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Values of the outputs and the linearization data (flat component arrays)."""
        flat, batch = self._flatten(xs, self.in_types)
        res = self._run("linearize", flat, batch)
        n_out = sum(O.SIZE[t] for t in self.out_types)
        bad = [k for k, r in enumerate(res) if not np.all(np.isfinite(r))]
        if bad:
            counters["nonfinite_linearization"] += 1
            raise NonFiniteError(self._explain_nonfinite(flat, batch))
        # data read many times (every CG product) is made contiguous once; broadcast constants stay views
        data = [np.broadcast_to(r, batch) for r in res[n_out:]]
        data = [d if d.flags.c_contiguous or 0 in d.strides else np.ascontiguousarray(d) for d in data]
        return self._unflatten(res[:n_out], self.out_types, batch), data

    def forward(self, data: list[np.ndarray], *dxs: Any) -> list[np.ndarray]:
        """J v: output gradients from input gradients (rotation vectors for quaternions)."""
        gt = [O.GRAD[t] for t in self.in_types]
        flat, batch = self._flatten(dxs, gt, np.shape(data[0]) if data else ())
        res = self._run("forward", list(data) + flat, batch)
        return self._unflatten(res, [O.GRAD[t] for t in self.out_types], batch)

    def reverse(self, data: list[np.ndarray], *gys: Any) -> list[np.ndarray]:
        """J^T w: input gradients from output gradients."""
        gt = [O.GRAD[t] for t in self.out_types]
        flat, batch = self._flatten(gys, gt, np.shape(data[0]) if data else ())
        res = self._run("reverse", list(data) + flat, batch)
        return self._unflatten(res, [O.GRAD[t] for t in self.in_types], batch)

    def accumulate(self, xs: Sequence[Any], dxs: Sequence[Any]) -> list[np.ndarray]:
        """x (+) dx per input (quaternion (+) rotation vector)."""
        f1, batch = self._flatten(xs, self.in_types)
        f2, batch = self._flatten(dxs, [O.GRAD[t] for t in self.in_types], batch)
        return self._unflatten(self._run("accumulate", f1 + f2, batch), self.in_types, batch)

    def _flatten(self, xs: Sequence[Any], types: list[str], batch: tuple[int, ...] = ()) -> tuple[list[Any], tuple]:
        if len(xs) != len(types):
            raise ValueError(f"expected {len(types)} arguments ({', '.join(types)}), got {len(xs)}")
        flat = []
        for x, t in zip(xs, types, strict=False):
            flat += _comps(x, t)
        batch = np.broadcast_shapes(batch, *[np.shape(c) for c in flat])
        return flat, batch

    def _unflatten(self, res: list[Any], types: list[str], batch: tuple[int, ...]) -> list[np.ndarray]:
        out, i = [], 0
        for t in types:
            n = O.SIZE[t]
            out.append(_pack(res[i:i + n], t, batch))
            i += n
        return out

    def _explain_nonfinite(self, flat: list[Any], batch: tuple[int, ...]) -> str:
        prog = self.scalar["linearize"]
        for i, x in zip(prog.inputs, flat, strict=False):
            if not np.all(np.isfinite(x)):
                return f"non-finite input {prog.nodes[i].name}"
        first: list[int] = []

        def see(i: int, v: Any) -> None:
            if not first and not np.all(np.isfinite(v)):
                first.append(i)

        self._run("linearize", flat, batch, see)
        node = prog.nodes[first[0]] if first else None
        if node is None or node.origin < 0:
            return "non-finite value in the linearization"
        ins = self.block["linearize"].instrs[node.origin]
        return f"non-finite value from instruction {ins.op} ({node.op} of its scalars) at {ins.line or '?'}"


@dataclass
class CData:
    """Linearization data of a batch in emit_c's "lanes" layout, as the C programs read it."""

    lanes: np.ndarray      # (groups, scalars, LANES)
    batch: tuple[int, ...]

    def arrays(self) -> list[np.ndarray]:
        """The numpy plan's form: one array per data scalar."""
        return list(from_lanes(self.lanes, int(np.prod(self.batch))).reshape((-1,) + self.batch))


_NO_OUTPUT = np.empty((0, 0))  # the unused second output segment of forward and reverse


def _size(types: list[str]) -> int:
    return sum(O.SIZE[t] for t in types)


class CLinearized(Linearized):
    """`Linearized` with the four programs compiled to C, each run in one call per batch on
    packed arrays: inputs and gradients as rows (one (n, width) block, a sample's values
    contiguous), the linearization data as a `CData`. The `*_rows` methods take and return the
    packed blocks directly; the others pack and unpack typed arrays around them."""

    def __post_init__(self) -> None:
        gi, go = [O.GRAD[t] for t in self.in_types], [O.GRAD[t] for t in self.out_types]
        nd = len(self.scalar["linearize"].outputs) - _size(self.out_types)  # stored data scalars
        self.widths = {"in": _size(self.in_types), "out": _size(self.out_types), "grad_in": _size(gi),
                       "grad_out": _size(go), "data": nd}
        w = self.widths
        self.exe = {
            "linearize": CProgram(self.scalar["linearize"], "autolin_linearize", ins=[("rows", w["in"])],
                                  outs=[("rows", w["out"]), ("lanes", nd)]),
            "forward": CProgram(self.scalar["forward"], "autolin_forward", ins=[("lanes", nd), ("rows", w["grad_in"])],
                                outs=[("rows", w["grad_out"])]),
            "reverse": CProgram(self.scalar["reverse"], "autolin_reverse", ins=[("lanes", nd), ("rows", w["grad_out"])],
                                outs=[("rows", w["grad_in"])]),
            "accumulate": CProgram(self.scalar["accumulate"], "autolin_accumulate",
                                   ins=[("rows", w["in"]), ("rows", w["grad_in"])], outs=[("rows", w["in"])])}

    def linearize_rows(self, x: np.ndarray) -> tuple[np.ndarray, CData]:
        """Output values (n, out width) and the data from the inputs packed as (n, in width)."""
        y, z = self.exe["linearize"].run(len(x), x)  # type: ignore[attr-defined]
        if not (np.isfinite(y).all() and np.isfinite(z).all()):
            counters["nonfinite_linearization"] += 1
            raise NonFiniteError(self._explain_nonfinite(list(x.T), (len(x),)))
        return y, CData(z, (len(x),))

    def forward_rows(self, data: CData, dx: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """J v on packed rows: (n, grad-in width) -> (n, grad-out width), into `out` if given."""
        return self._rows_call("forward", data, dx, out)

    def reverse_rows(self, data: CData, w: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """J^T w on packed rows: (n, grad-out width) -> (n, grad-in width), into `out` if given."""
        return self._rows_call("reverse", data, w, out)

    def _rows_call(self, name: str, data: CData, x: np.ndarray, out: np.ndarray | None) -> np.ndarray:
        prog: CProgram = self.exe[name]  # type: ignore[assignment]
        return prog.run(len(x), data.lanes, x, None if out is None else (out, _NO_OUTPUT))[0]

    def linearize(self, *xs: Any) -> tuple[list[np.ndarray], CData]:  # type: ignore[override]
        x, batch = _rows(xs, self.in_types)
        y, d = self.linearize_rows(x)
        d.batch = batch
        return _unrows(y, self.out_types, batch), d

    def forward(self, data: CData | list[np.ndarray], *dxs: Any) -> list[np.ndarray]:  # type: ignore[override]
        d = self._data(data)
        dx, batch = _rows(dxs, [O.GRAD[t] for t in self.in_types], d.batch)
        return _unrows(self.forward_rows(d, dx), [O.GRAD[t] for t in self.out_types], batch)

    def reverse(self, data: CData | list[np.ndarray], *gys: Any) -> list[np.ndarray]:  # type: ignore[override]
        d = self._data(data)
        w, batch = _rows(gys, [O.GRAD[t] for t in self.out_types], d.batch)
        return _unrows(self.reverse_rows(d, w), [O.GRAD[t] for t in self.in_types], batch)

    def accumulate(self, xs: Sequence[Any], dxs: Sequence[Any]) -> list[np.ndarray]:
        x, batch = _rows(xs, self.in_types)
        dx, batch = _rows(dxs, [O.GRAD[t] for t in self.in_types], batch)
        y, _ = self.exe["accumulate"].run(len(x), x, dx)  # type: ignore[attr-defined]
        return _unrows(y, self.in_types, batch)

    def _data(self, data: CData | list[np.ndarray]) -> CData:
        if isinstance(data, CData):
            return data
        batch = np.broadcast_shapes(*[np.shape(a) for a in data])  # the numpy plan's data: repacked
        cols = np.array([np.broadcast_to(a, batch).ravel() for a in data]).reshape(len(data), -1)
        return CData(to_lanes(cols), batch)


def _rows(xs: Sequence[Any], types: list[str], batch: tuple[int, ...] = ()) -> tuple[np.ndarray, tuple[int, ...]]:
    """Typed arrays (broadcast over the batch) packed into one (n, width) C-order block."""
    if len(xs) != len(types):
        raise ValueError(f"expected {len(types)} arguments ({', '.join(types)}), got {len(xs)}")
    arrs = [np.asarray(x, dtype=float) for x in xs]
    trail = [O.SHAPE[t] for t in types]
    for a, t, s in zip(arrs, types, trail, strict=True):
        if a.shape[a.ndim - len(s):] != s or a.ndim < len(s):
            raise ValueError(f"a {t} needs trailing shape {s}, got {a.shape}")
    batch = np.broadcast_shapes(batch, *[a.shape[:a.ndim - len(s)] for a, s in zip(arrs, trail, strict=True)])
    n = int(np.prod(batch))
    out = np.empty((n, _size(types)))
    k = 0
    for a, t, s in zip(arrs, types, trail, strict=True):
        m = O.SIZE[t]
        out[:, k:k + m] = np.broadcast_to(a, batch + s).reshape(n, m)
        k += m
    return out, batch


def _unrows(y: np.ndarray, types: list[str], batch: tuple[int, ...]) -> list[np.ndarray]:
    out, k = [], 0
    for t in types:
        m = O.SIZE[t]
        out.append(y[:, k:k + m].reshape(batch + O.SHAPE[t]))
        k += m
    return out


def generate(src: Program) -> Linearized:
    """The four programs of a recorded program, lowered and simplified."""
    lin, _ = linearization_program(src)
    block = {"linearize": lin, "forward": forward_program(src), "reverse": reverse_program(src),
             "accumulate": accumulation_program(src)}
    scal: dict[str, S.ScalarProgram] = {}
    lp, sizes = lower(lin)
    # linearization data that is the same finite constant for every sample (a constant axis, a
    # derivative factor of a linear operator) is folded into forward and reverse, not stored;
    # data equal to earlier data (an argument several linearizers keep) is stored once
    n_out = len(lp.outputs) - sum(sizes)
    data = lp.outputs[n_out:]
    consts = {k: float(lp.nodes[o].value) for k, o in enumerate(data)
              if lp.nodes[o].op in ("const", "zero") and np.isfinite(lp.nodes[o].value)}
    first: dict[int, int] = {}
    alias = {k: first.setdefault(o, k) for k, o in enumerate(data) if k not in consts}
    alias = {k: j for k, j in alias.items() if j != k}
    lp.outputs = lp.outputs[:n_out] + [o for k, o in enumerate(data) if k not in consts and k not in alias]
    scal["linearize"] = S.prune(lp)
    for name in ("forward", "reverse"):
        scal[name], _ = lower(block[name], sizes, consts, alias)
    scal["accumulate"], _ = lower(block["accumulate"])
    return Linearized(src, block, scal, sizes)


def compile(fn: Callable[..., Any], types: Sequence[str]) -> Linearized:  # noqa: A001 - the library's verb
    """Traces `fn` once on inputs of `types` and generates its programs."""
    return generate(trace(fn, types))
