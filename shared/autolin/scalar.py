"""Scalar programs: the lowest level of autolin.

A scalar program is an SSA graph of scalar nodes (inputs, constants, arithmetic) in
topological order. Block programs are lowered to scalar programs by running their
operator implementations on `Sym` values; the same `replay` runs a scalar program on
numpy arrays (batched execution) or on `Sym` values (inlining). The module also holds the
framework's own scalar automatic differentiation (`jvp_program`, `vjp_program`), used as
the baseline the block operators are counted and validated against, and the
simplification pass of thesis section 3.2.5.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

ARITH = ("add", "sub", "mul", "neg", "div")
NONLINEAR = ("sin", "cos", "sqrt")
_UNARY_NP: dict[str, Callable[[Any], Any]] = {"sin": np.sin, "cos": np.cos, "sqrt": np.sqrt}


@dataclass
class Node:
    op: str                      # "in", "const", "zero", "mov" or one of ARITH / NONLINEAR
    args: tuple[int, ...] = ()
    value: float = 0.0           # constants only
    name: str = ""               # inputs only
    origin: int = -1             # index of the block instruction this node was lowered from


@dataclass
class ScalarProgram:
    nodes: list[Node] = field(default_factory=list)
    inputs: list[int] = field(default_factory=list)
    outputs: list[int] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        """Arithmetic instructions reachable from the outputs, by kind, plus memory operations:
        loads are the distinct input scalars read, stores the outputs an instruction writes
        (an output that is an input or a constant is a pass-through, not a store)."""
        live = self.live()
        c = {k: 0 for k in ARITH + NONLINEAR}
        loads = set()
        for i in live:
            n = self.nodes[i]
            if n.op in c:
                c[n.op] += 1
                loads.update(a for a in n.args if self.nodes[a].op == "in")
        stores = {o for o in self.outputs if self.nodes[o].op in c}
        c["muls"] = c["mul"] + c["div"]
        c["adds"] = c["add"] + c["sub"] + c["neg"]
        c["instructions"] = sum(c[k] for k in ARITH + NONLINEAR)
        c["loads"], c["stores"] = len(loads), len(stores)
        c["memory_ops"] = len(loads) + len(stores)
        return c

    def live(self) -> list[int]:
        seen = set(self.outputs)
        for i in range(len(self.nodes) - 1, -1, -1):
            if i in seen:
                seen.update(self.nodes[i].args)
        return sorted(seen)

    def listing(self) -> str:
        out = []
        for i in self.live():
            n = self.nodes[i]
            if n.op == "in":
                rhs = f"in {n.name}"
            elif n.op in ("const", "zero"):
                rhs = f"{n.value!r}"
            else:
                rhs = f"{n.op} " + ", ".join(f"s{a}" for a in n.args)
            out.append(f"s{i} = {rhs}")
        out.append("return " + ", ".join(f"s{o}" for o in self.outputs))
        return "\n".join(out)


class Builder:
    """Emits nodes; with `simplify` it folds constants, deduplicates equal constants, maps
    operations on zero and one to zero operators and moves, and skips moves."""

    def __init__(self, simplify: bool = True) -> None:
        self.prog = ScalarProgram()
        self.simplify = simplify
        self._consts: dict[float, int] = {}
        self.origin = -1

    def input(self, name: str) -> Sym:
        self.prog.nodes.append(Node("in", name=name, origin=self.origin))
        i = len(self.prog.nodes) - 1
        self.prog.inputs.append(i)
        return Sym(self, i)

    def const(self, v: float) -> Sym:
        v = float(v)
        if self.simplify and v in self._consts and not np.isnan(v):
            return Sym(self, self._consts[v])
        self.prog.nodes.append(Node("zero" if v == 0.0 else "const", value=v, origin=self.origin))
        self._consts[v] = len(self.prog.nodes) - 1
        return Sym(self, self._consts[v])

    def _cval(self, s: Sym) -> float | None:
        n = self.prog.nodes[s.i]
        return n.value if n.op in ("const", "zero") else None

    def emit(self, op: str, *args: Sym) -> Sym:
        if self.simplify:
            r = self._peephole(op, args)
            if r is not None:
                return r
        if op == "mov":
            return args[0]
        self.prog.nodes.append(Node(op, tuple(a.i for a in args), origin=self.origin))
        return Sym(self, len(self.prog.nodes) - 1)

    def _peephole(self, op: str, args: Sequence[Sym]) -> Sym | None:
        cv = [self._cval(a) for a in args]
        if op == "mov":
            return args[0]
        if all(c is not None for c in cv):  # constant folding
            vals = [np.float64(c) for c in cv]
            with np.errstate(all="ignore"):
                return self.const(float(_apply(op, vals)))
        if op == "add":
            if cv[0] == 0.0:
                return args[1]
            if cv[1] == 0.0:
                return args[0]
        elif op == "sub":
            if cv[1] == 0.0:
                return args[0]
            if cv[0] == 0.0:
                return self.emit("neg", args[1])
            if args[0].i == args[1].i:
                return self.const(0.0)
        elif op == "mul":
            for k in (0, 1):
                if cv[k] == 0.0:
                    return self.const(0.0)
                if cv[k] == 1.0:
                    return args[1 - k]
                if cv[k] == -1.0:
                    return self.emit("neg", args[1 - k])
        elif op == "div" and cv[1] == 1.0:
            return args[0]
        elif op == "neg" and self.prog.nodes[args[0].i].op == "neg":
            return Sym(self, self.prog.nodes[args[0].i].args[0])
        return None


def _apply(op: str, a: Sequence[Any]) -> Any:
    if op == "add":
        return a[0] + a[1]
    if op == "sub":
        return a[0] - a[1]
    if op == "mul":
        return a[0] * a[1]
    if op == "div":
        return a[0] / a[1]
    if op == "neg":
        return -a[0]
    if op == "mov":
        return a[0]
    if isinstance(a[0], Sym):
        return a[0].b.emit(op, a[0])
    return _UNARY_NP[op](a[0])


class Sym:
    """A traced scalar: arithmetic on it emits nodes into its builder."""

    __slots__ = ("b", "i")
    __array_priority__ = 1000  # numpy scalars defer to Sym's operators

    def __init__(self, b: Builder, i: int) -> None:
        self.b, self.i = b, i

    def _w(self, o: Any) -> Sym:
        return o if isinstance(o, Sym) else self.b.const(float(o))

    def __add__(self, o: Any) -> Sym:
        return self.b.emit("add", self, self._w(o))

    def __radd__(self, o: Any) -> Sym:
        return self.b.emit("add", self._w(o), self)

    def __sub__(self, o: Any) -> Sym:
        return self.b.emit("sub", self, self._w(o))

    def __rsub__(self, o: Any) -> Sym:
        return self.b.emit("sub", self._w(o), self)

    def __mul__(self, o: Any) -> Sym:
        return self.b.emit("mul", self, self._w(o))

    def __rmul__(self, o: Any) -> Sym:
        return self.b.emit("mul", self._w(o), self)

    def __truediv__(self, o: Any) -> Sym:
        return self.b.emit("div", self, self._w(o))

    def __rtruediv__(self, o: Any) -> Sym:
        return self.b.emit("div", self._w(o), self)

    def __neg__(self) -> Sym:
        return self.b.emit("neg", self)


def sin(x: Any) -> Any:
    return x.b.emit("sin", x) if isinstance(x, Sym) else np.sin(x)


def cos(x: Any) -> Any:
    return x.b.emit("cos", x) if isinstance(x, Sym) else np.cos(x)


def sqrt(x: Any) -> Any:
    return x.b.emit("sqrt", x) if isinstance(x, Sym) else np.sqrt(x)


def replay(prog: ScalarProgram, inputs: Sequence[Any], on_node: Callable[[int, Any], None] | None = None,
           builder: Builder | None = None) -> list[Any]:
    """Run `prog` on numpy arrays (batched execution), or inline it into `builder` when the
    inputs are `Sym` values. `on_node(i, value)` sees every computed node (error reports)."""
    vals: list[Any] = [None] * len(prog.nodes)
    for i, x in zip(prog.inputs, inputs, strict=False):
        vals[i] = x
    for i in prog.live():
        n = prog.nodes[i]
        if n.op == "in":
            continue
        if n.op in ("const", "zero"):
            vals[i] = builder.const(n.value) if builder is not None else n.value
            continue
        if builder is not None:
            builder.origin = n.origin
        with np.errstate(all="ignore"):
            vals[i] = _apply(n.op, [vals[a] for a in n.args])
        if on_node is not None:
            on_node(i, vals[i])
    return [vals[o] for o in prog.outputs]


def simplify(prog: ScalarProgram) -> ScalarProgram:
    """Section 3.2.5: constant folding, equal constants deduplicated, zero operators,
    redundant moves skipped (all by re-emitting through a simplifying builder), then
    unused constants and instructions removed."""
    b = Builder(simplify=True)
    ins = [b.input(prog.nodes[i].name) for i in prog.inputs]
    outs = replay(prog, ins, builder=b)
    b.prog.outputs = [o.i for o in outs]
    return prune(b.prog)


def prune(prog: ScalarProgram) -> ScalarProgram:
    """Drops nodes no output depends on (inputs are kept: they are the program's signature)."""
    keep = sorted(set(prog.live()) | set(prog.inputs))
    remap = {old: new for new, old in enumerate(keep)}
    nodes = []
    for old in keep:
        n = prog.nodes[old]
        nodes.append(Node(n.op, tuple(remap[a] for a in n.args), n.value, n.name, n.origin))
    return ScalarProgram(nodes, [remap[i] for i in prog.inputs], [remap[o] for o in prog.outputs])


def trace_scalar(fn: Callable[..., Sequence[Any]], names: Sequence[str]) -> ScalarProgram:
    """Records `fn(*scalars) -> sequence of scalars` into a scalar program."""
    b = Builder(simplify=True)
    outs = fn(*[b.input(n) for n in names])
    b.prog.outputs = [(o if isinstance(o, Sym) else b.const(o)).i for o in outs]
    return b.prog


def jvp_program(prog: ScalarProgram) -> ScalarProgram:
    """Scalar forward-mode AD: inputs are the values then one tangent per value, outputs
    the output tangents. The baseline of the instruction counts."""
    b = Builder(simplify=True)
    xs = [b.input(prog.nodes[i].name) for i in prog.inputs]
    dxs = [b.input("d" + prog.nodes[i].name) for i in prog.inputs]
    v: dict[int, Any] = dict(zip(prog.inputs, xs, strict=False))
    d: dict[int, Any] = dict(zip(prog.inputs, dxs, strict=False))
    zero = b.const(0.0)
    for i in prog.live():
        n = prog.nodes[i]
        if n.op == "in":
            continue
        if n.op in ("const", "zero"):
            v[i], d[i] = b.const(n.value), zero
            continue
        a = [v[k] for k in n.args]
        da = [d[k] for k in n.args]
        v[i] = _apply(n.op, a)
        if n.op in ("add", "sub"):
            d[i] = _apply(n.op, da)
        elif n.op == "neg":
            d[i] = -da[0]
        elif n.op == "mul":
            d[i] = da[0] * a[1] + a[0] * da[1]
        elif n.op == "div":
            d[i] = (da[0] - v[i] * da[1]) / a[1]
        elif n.op == "sin":
            d[i] = da[0] * cos(a[0])
        elif n.op == "cos":
            d[i] = -(da[0] * sin(a[0]))
        elif n.op == "sqrt":
            d[i] = da[0] / (v[i] + v[i])
    b.prog.outputs = [d[o].i for o in prog.outputs]
    return prune(b.prog)


def vjp_program(prog: ScalarProgram) -> ScalarProgram:
    """Scalar reverse-mode AD: inputs are the values then one cotangent per output, outputs
    the input gradients. Signs are carried lazily so `-g` costs no negation; contributions
    to a node read more than once are merged in a binary tree."""
    b = Builder(simplify=True)
    xs = [b.input(prog.nodes[i].name) for i in prog.inputs]
    gys = [b.input("g" + str(k)) for k in range(len(prog.outputs))]
    v: dict[int, Any] = dict(zip(prog.inputs, xs, strict=False))
    live = prog.live()
    for i in live:  # forward sweep: values needed by the reverse rules
        n = prog.nodes[i]
        if n.op in ("const", "zero"):
            v[i] = b.const(n.value)
        elif n.op != "in":
            v[i] = _apply(n.op, [v[k] for k in n.args])
    contrib: dict[int, list[tuple[Sym, int]]] = {}
    for o, g in zip(prog.outputs, gys, strict=False):
        contrib.setdefault(o, []).append((g, 1))
    grads: dict[int, tuple[Sym, int]] = {}
    for i in reversed(live):
        n = prog.nodes[i]
        if i not in contrib:
            continue
        g, s = merge_signed(contrib.pop(i))
        if n.op == "in":
            grads[i] = (g, s)
            continue
        a = [v[k] for k in n.args]
        parts: list[tuple[Sym, int]] = []
        if n.op == "add":
            parts = [(g, s), (g, s)]
        elif n.op == "sub":
            parts = [(g, s), (g, -s)]
        elif n.op == "neg":
            parts = [(g, -s)]
        elif n.op == "mul":
            parts = [(g * a[1], s), (g * a[0], s)]
        elif n.op == "div":
            q = g / a[1]
            parts = [(q, s), (q * v[i], -s)]
        elif n.op == "sin":
            parts = [(g * cos(a[0]), s)]
        elif n.op == "cos":
            parts = [(g * sin(a[0]), -s)]
        elif n.op == "sqrt":
            parts = [(g / (v[i] + v[i]), s)]
        for k, p in zip(n.args, parts, strict=False):
            if prog.nodes[k].op not in ("const", "zero"):
                contrib.setdefault(k, []).append(p)
    outs = []
    for i in prog.inputs:
        g, s = grads.get(i, (b.const(0.0), 1))
        outs.append(g if s > 0 else -g)
    b.prog.outputs = [o.i for o in outs]
    return prune(b.prog)


def merge_signed(terms: list[tuple[Sym, int]]) -> tuple[Sym, int]:
    """Sums signed terms in a binary tree; a difference costs one instruction like a sum."""
    pos = [t for t, s in terms if s > 0]
    neg = [t for t, s in terms if s < 0]
    if not pos:
        return tree_sum(neg), -1
    if not neg:
        return tree_sum(pos), 1
    return tree_sum(pos) - tree_sum(neg), 1


def tree_sum(xs: list[Any]) -> Any:
    while len(xs) > 1:
        xs = [xs[k] + xs[k + 1] if k + 1 < len(xs) else xs[k] for k in range(0, len(xs), 2)]
    return xs[0]
