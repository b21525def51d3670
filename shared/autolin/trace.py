"""Recording a program by operator overloading (thesis section 3.2).

`trace(fn, types)` calls `fn` once with traced values (`Scalar`, `Vec3`, `Quat`, `Mat3`, `Rot3`);
their operators append block instructions to a `Program`. Branching on a traced value is
data-dependent control flow, which a recording cannot represent: it raises `TracingError`
naming the user's line.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import ops as O

_HERE = os.path.dirname(os.path.abspath(__file__))


class TracingError(RuntimeError):
    """The traced code did something a recorded program cannot represent."""


def user_line() -> str:
    """file:line of the innermost caller outside this package."""
    f = sys._getframe(1)
    while f is not None and os.path.dirname(os.path.abspath(f.f_code.co_filename)) == _HERE:
        f = f.f_back
    return f"{f.f_code.co_filename}:{f.f_lineno}" if f is not None else "?"


@dataclass
class Instr:
    op: str
    args: tuple[int, ...]
    outs: tuple[int, ...]
    line: str = ""


@dataclass
class Program:
    """A block program: typed variables, constants, instructions in order."""

    name: str = "nonlinear"
    types: list[str] = field(default_factory=list)
    consts: dict[int, tuple[float, ...]] = field(default_factory=dict)
    instrs: list[Instr] = field(default_factory=list)
    inputs: list[int] = field(default_factory=list)
    outputs: list[int] = field(default_factory=list)

    def var(self, typ: str) -> int:
        self.types.append(typ)
        return len(self.types) - 1

    def listing(self) -> str:
        def name(v: int) -> str:
            return f"c{v}" if v in self.consts else f"v{v}"
        lines = [f"{self.name}({', '.join(f'{name(v)}: {self.types[v]}' for v in self.inputs)}):"]
        for v, c in self.consts.items():
            lines.append(f"  c{v}: {self.types[v]} = {list(c)}")
        for ins in self.instrs:
            lines.append(f"  {', '.join(name(o) for o in ins.outs)} = {ins.op}({', '.join(name(a) for a in ins.args)})")
        lines.append(f"  return {', '.join(name(o) for o in self.outputs)}")
        return "\n".join(lines)


class Tracer:
    def __init__(self) -> None:
        self.prog = Program()

    def const(self, typ: str, comps: Sequence[float]) -> Value:
        v = self.prog.var(typ)
        self.prog.consts[v] = tuple(float(c) for c in comps)
        return WRAP[typ](self, v)

    def emit(self, op: str, *args: Value) -> Value:
        o = O.OPS[op]
        if tuple(a.typ for a in args) != o.arg_types:
            raise TracingError(f"{user_line()}: {op} takes {o.arg_types}, got {tuple(a.typ for a in args)}")
        v = self.prog.var(o.out_type)
        self.prog.instrs.append(Instr(op, tuple(a.v for a in args), (v,), user_line()))
        return WRAP[o.out_type](self, v)


def lift(tr: Tracer, o: Any, typ: str) -> Value:
    """A traced value of `tr` as is, or a plain number / array as a constant of type `typ`."""
    if isinstance(o, Value):
        if o.tr is not tr:
            raise TracingError(f"{user_line()}: value from another trace")
        return o
    if isinstance(o, (int, float, np.floating, np.integer, np.ndarray, list, tuple)):
        c = np.asarray(o, dtype=float).ravel()
        if c.size != O.SIZE[typ]:
            raise TracingError(f"{user_line()}: constant of {c.size} numbers where a {typ} is needed")
        return tr.const(typ, c)
    raise TracingError(f"{user_line()}: cannot use {type(o).__name__} where a {typ} is needed")


class Value:
    typ = ""

    def __init__(self, tr: Tracer, v: int) -> None:
        self.tr, self.v = tr, v

    def _lift(self, o: Any, typ: str) -> Value:
        return lift(self.tr, o, typ)

    def _nocontrol(self, *_: Any) -> bool:
        raise TracingError(f"{user_line()}: data-dependent control flow on a traced {self.typ} (comparison "
                           "or truth test) cannot be recorded; use arithmetic instead of branching")

    __bool__ = __lt__ = __le__ = __gt__ = __ge__ = _nocontrol  # type: ignore[assignment]
    __float__ = __int__ = __index__ = _nocontrol  # type: ignore[assignment]

    def __eq__(self, o: object) -> bool:  # type: ignore[override]
        return self._nocontrol()

    __hash__ = object.__hash__


class _Linear(Value):
    """Values with + and - of their own type and unary minus."""

    def __add__(self, o: Any) -> Value:
        return self.tr.emit(f"add.{self.typ}", self, self._lift(o, self.typ))

    def __radd__(self, o: Any) -> Value:
        return self.tr.emit(f"add.{self.typ}", self._lift(o, self.typ), self)

    def __sub__(self, o: Any) -> Value:
        return self.tr.emit(f"sub.{self.typ}", self, self._lift(o, self.typ))

    def __rsub__(self, o: Any) -> Value:
        return self.tr.emit(f"sub.{self.typ}", self._lift(o, self.typ), self)

    def __neg__(self) -> Value:
        return self.tr.emit(f"neg.{self.typ}", self)


class Scalar(_Linear):
    typ = "scalar"

    def __mul__(self, o: Any) -> Value:
        if isinstance(o, Vec3):
            return self.tr.emit("scale", self, o)
        return self.tr.emit("mul", self, self._lift(o, "scalar"))

    def __rmul__(self, o: Any) -> Value:
        return self.tr.emit("mul", self._lift(o, "scalar"), self)

    def __truediv__(self, o: Any) -> Value:
        return self.tr.emit("div", self, self._lift(o, "scalar"))

    def __rtruediv__(self, o: Any) -> Value:
        return self.tr.emit("div", self._lift(o, "scalar"), self)


class Vec3(_Linear):
    typ = "vec3"

    def __mul__(self, s: Any) -> Value:
        return self.tr.emit("scale", self._lift(s, "scalar"), self)

    __rmul__ = __mul__


class Mat3(_Linear):
    typ = "mat3"

    def __matmul__(self, o: Any) -> Value:
        if isinstance(o, Vec3):
            return self.tr.emit("matvec", self, o)
        return self.tr.emit("matmul", self, self._lift(o, "mat3"))

    def __rmatmul__(self, o: Any) -> Value:
        return self.tr.emit("matmul", self._lift(o, "mat3"), self)


class Quat(Value):
    typ = "quat"

    def __mul__(self, o: Any) -> Value:
        """Quaternion product, or rotation of a vector (q v q*)."""
        if isinstance(o, Vec3):
            return self.tr.emit("rotate", self, o)
        return self.tr.emit("qmul", self, self._lift(o, "quat"))

    def __rmul__(self, o: Any) -> Value:
        return self.tr.emit("qmul", self._lift(o, "quat"), self)

    def conj(self) -> Value:
        return self.tr.emit("conj", self)


class Rot3(Value):
    """A rotation matrix; its gradient is a rotation vector."""

    typ = "rot3"

    def __matmul__(self, o: Any) -> Value:
        """Rotation chaining, or rotation of a vector."""
        if isinstance(o, Vec3):
            return self.tr.emit("rrotate", self, o)
        return self.tr.emit("rmul", self, self._lift(o, "rot3"))


WRAP: dict[str, type[Value]] = {"scalar": Scalar, "vec3": Vec3, "quat": Quat, "mat3": Mat3, "rot3": Rot3}


def _tracer_of(*xs: Any) -> Tracer:
    for x in xs:
        if isinstance(x, Value):
            return x.tr
    raise TracingError(f"{user_line()}: no traced value among the arguments")


def sin(x: Scalar) -> Value:
    return x.tr.emit("sin", x)


def cos(x: Scalar) -> Value:
    return x.tr.emit("cos", x)


def sqrt(x: Scalar) -> Value:
    return x.tr.emit("sqrt", x)


def dot(a: Any, b: Any) -> Value:
    tr = _tracer_of(a, b)
    return tr.emit("dot", lift(tr, a, "vec3"), lift(tr, b, "vec3"))


def cross(a: Any, b: Any) -> Value:
    tr = _tracer_of(a, b)
    return tr.emit("cross", lift(tr, a, "vec3"), lift(tr, b, "vec3"))


def angle_axis(angle: Scalar, axis: Sequence[float]) -> Value:
    """Quaternion rotating by the traced `angle` about a constant axis (normalized here)."""
    if isinstance(axis, Value):
        raise TracingError(f"{user_line()}: angle_axis takes a constant axis; rotate a constant axis with "
                           "a traced quaternion to move it")
    a = np.asarray(axis, dtype=float)
    n = float(np.linalg.norm(a))
    if a.shape != (3,) or not np.isfinite(n) or n == 0.0:
        raise TracingError(f"{user_line()}: angle_axis needs a finite non-zero 3-vector axis, got {axis!r}")
    return angle.tr.emit(O.angle_axis_op(tuple(a / n)).name, angle)


def to_matrix(q: Quat) -> Value:
    """The rotation matrix of a unit quaternion (same rotation-vector gradient)."""
    return q.tr.emit("to_matrix", q)


def call(op: str, *args: Value) -> Value:
    """Applies a registered operator (e.g. a user operator added with `ops.register`)."""
    return _tracer_of(*args).emit(op, *args)


def trace(fn: Callable[..., Any], types: Sequence[str]) -> Program:
    """Records `fn` once on traced inputs of the given types."""
    bad = [t for t in types if t not in WRAP]
    if bad:
        raise ValueError(f"unknown input types {bad}; known: {sorted(WRAP)}")
    tr = Tracer()
    ins = []
    for t in types:
        v = tr.prog.var(t)
        tr.prog.inputs.append(v)
        ins.append(WRAP[t](tr, v))
    try:
        out = fn(*ins)
        outs = list(out) if isinstance(out, (tuple, list)) else [out]
        for o in outs:
            if not isinstance(o, Value) or o.tr is not tr:
                raise TracingError(f"{getattr(fn, '__name__', 'fn')} returned {type(o).__name__}, not a value "
                                   "traced from its inputs")
    except TracingError:
        O.counters["tracing_error"] += 1
        raise
    tr.prog.outputs = [o.v for o in outs]
    return tr.prog
