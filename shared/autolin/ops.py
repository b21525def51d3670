"""Block operators and their linearizers (thesis section 3.2.6).

A value is a tuple of scalar components (numpy arrays for batched execution, `Sym` when a
program is lowered). Each operator has a non-linear `eval`, and either a linearizer with
forward and reverse rules that use only its stored data (multiplies and adds), or none:
then the plain rule applies (the framework's scalar AD of `eval`, on the arguments).

Types and their gradient types: scalar -> scalar, vec3 -> vec3, mat3 -> mat3 (row-major),
quat (w, x, y, z, unit) -> vec3 rotation vector, with the perturbation q' = exp(v) q, and
rot3 (rotation matrix, row-major) -> vec3 rotation vector, R' = exp([v]x) R.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from . import scalar as S

log = logging.getLogger(__name__)

SIZE = {"scalar": 1, "vec3": 3, "quat": 4, "mat3": 9, "rot3": 9}
GRAD = {"scalar": "scalar", "vec3": "vec3", "quat": "vec3", "mat3": "mat3", "rot3": "vec3"}
SHAPE = {"scalar": (), "vec3": (3,), "quat": (4,), "mat3": (3, 3), "rot3": (3, 3)}  # trailing array shapes

Comps = tuple[Any, ...]
counters: Counter[str] = Counter()  # bad input met by tracing and execution, by kind


# --- component arithmetic, shared by every execution path -------------------------------
def cross(a: Comps, b: Comps) -> Comps:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def dot(a: Comps, b: Comps) -> Any:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def vadd(a: Comps, b: Comps) -> Comps:
    return tuple(x + y for x, y in zip(a, b, strict=False))


def qrot(q: Comps, v: Comps) -> Comps:
    """q v q*: t = 2 (r x v), v + w t + r x t, 15 multiplies and 15 additions."""
    t = cross(q[1:], v)
    t = (t[0] + t[0], t[1] + t[1], t[2] + t[2])
    c = cross(q[1:], t)
    return tuple(v[k] + q[0] * t[k] + c[k] for k in range(3))


def qrot_conj(q: Comps, v: Comps) -> Comps:
    """q* v q with the same method and reversed signs (crosses swapped): 30 instructions."""
    t = cross(v, q[1:])
    t = (t[0] + t[0], t[1] + t[1], t[2] + t[2])
    c = cross(t, q[1:])
    return tuple(v[k] + q[0] * t[k] + c[k] for k in range(3))


def qmul(a: Comps, b: Comps) -> Comps:
    return (a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
            a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
            a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
            a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0])


def matmul(a: Comps, b: Comps) -> Comps:
    return tuple(a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j]
                 for i in range(3) for j in range(3))


def matvec(a: Comps, v: Comps) -> Comps:
    return tuple(a[3 * i] * v[0] + a[3 * i + 1] * v[1] + a[3 * i + 2] * v[2] for i in range(3))


def transpose(a: Comps) -> Comps:
    return tuple(a[3 * j + i] for i in range(3) for j in range(3))


def retract(q: Comps, v: Comps) -> Comps:
    """q (+) v: normalize(q + 1/2 [0, v] q), first-order equal to exp(v) q, no trigonometry."""
    d = qmul((0.0, v[0], v[1], v[2]), q)
    p = tuple(q[k] + 0.5 * d[k] for k in range(4))
    n = S.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2] + p[3] * p[3])
    return tuple(x / n for x in p)


def cayley(r: Comps, v: Comps) -> Comps:
    """R (+) v: cay(v) R, cay(v) = I + k ([u]x + [u]x^2), u = v/2, k = 2 / (1 + |u|^2): exactly
    orthogonal and equal to exp([v]x) to second order, with no trigonometry."""
    u = (0.5 * v[0], 0.5 * v[1], 0.5 * v[2])
    uu = dot(u, u)
    k = 2.0 / (1.0 + uu)
    ux = (0.0, -u[2], u[1], u[2], 0.0, -u[0], -u[1], u[0], 0.0)
    m = tuple((1.0 if i == j else 0.0) + k * (ux[3 * i + j] + u[i] * u[j] - (uu if i == j else 0.0))
              for i in range(3) for j in range(3))
    return matmul(m, r)


def quat_to_matrix(q: Comps) -> Comps:
    w, x, y, z = q
    return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


def accumulate(typ: str, x: Comps, g: Comps) -> Comps:
    """The addition of a value and a gradient of its gradient type (section 3.2.4)."""
    if typ == "quat":
        return retract(x, g)
    return cayley(x, g) if typ == "rot3" else vadd(x, g)


# --- operator table ---------------------------------------------------------------------
@dataclass
class Op:
    name: str
    arg_types: tuple[str, ...]
    out_type: str
    eval: Callable[..., Comps]
    lin: Callable[..., tuple[Comps, ...]] | None = None   # (args..., out) -> data
    fwd: Callable[..., Comps] | None = None               # (data, dargs...) -> dout
    rev: Callable[..., tuple[Comps, ...]] | None = None   # (data, gout) -> dargs


OPS: dict[str, Op] = {}
_warned: set[str] = set()


def register(op: Op) -> Op:
    """Adds an operator. Without a linearizer the plain rule applies, which needs gradient
    types equal to value types (no quaternions), and says so once when first used."""
    if op.lin is None and {"quat", "rot3"} & set(op.arg_types + (op.out_type,)):
        raise ValueError(f"operator {op.name!r} on rotations needs a linearizer: its gradients are "
                         "rotation vectors, which the plain rule cannot produce")
    OPS[op.name] = op
    return op


def _scal(f: Callable[..., Any]) -> Callable[..., Comps]:
    return lambda *a: (f(*[x[0] for x in a]),)


def vsub(a: Comps, b: Comps) -> Comps:
    return tuple(x - y for x, y in zip(a, b, strict=True))


def _neg(v: Comps) -> Comps:
    return tuple(-x for x in v)


def _scale(s: Any, v: Comps) -> Comps:
    return tuple(s * x for x in v)


for _t in ("scalar", "vec3", "mat3"):
    register(Op(f"add.{_t}", (_t, _t), _t, vadd, lambda a, b, o: (), lambda L, da, db: vadd(da, db),
                lambda L, g: (g, g)))
    register(Op(f"sub.{_t}", (_t, _t), _t, vsub, lambda a, b, o: (),
                lambda L, da, db: vsub(da, db), lambda L, g: (g, _neg(g))))
    register(Op(f"neg.{_t}", (_t,), _t, _neg, lambda a, o: (), lambda L, da: _neg(da), lambda L, g: (_neg(g),)))

# scalar products keep both factors: forward and reverse are then multiplies and adds
register(Op("mul", ("scalar", "scalar"), "scalar", _scal(lambda a, b: a * b), lambda a, b, o: (a[0], b[0]),
            lambda L, da, db: (da[0] * L[1] + L[0] * db[0],), lambda L, g: ((g[0] * L[1],), (g[0] * L[0],))))
register(Op("div", ("scalar", "scalar"), "scalar", _scal(lambda a, b: a / b),
            lambda a, b, o: (1.0 / b[0], o[0] / b[0]),
            lambda L, da, db: (da[0] * L[0] - db[0] * L[1],), lambda L, g: ((g[0] * L[0],), (-(g[0] * L[1]),))))
# trigonometry: the linearizer stores the derivative factor once
register(Op("sin", ("scalar",), "scalar", _scal(S.sin), lambda a, o: (S.cos(a[0]),),
            lambda L, da: (da[0] * L[0],), lambda L, g: ((g[0] * L[0],),)))
register(Op("cos", ("scalar",), "scalar", _scal(S.cos), lambda a, o: (-S.sin(a[0]),),
            lambda L, da: (da[0] * L[0],), lambda L, g: ((g[0] * L[0],),)))
register(Op("sqrt", ("scalar",), "scalar", _scal(S.sqrt), lambda a, o: (0.5 / o[0],),
            lambda L, da: (da[0] * L[0],), lambda L, g: ((g[0] * L[0],),)))

register(Op("scale", ("scalar", "vec3"), "vec3", lambda s, v: _scale(s[0], v), lambda s, v, o: (s[0],) + tuple(v),
            lambda L, ds, dv: vadd(_scale(ds[0], L[1:]), _scale(L[0], dv)),
            lambda L, g: ((dot(g, L[1:]),), _scale(L[0], g))))
register(Op("dot", ("vec3", "vec3"), "scalar", lambda a, b: (dot(a, b),), lambda a, b, o: tuple(a) + tuple(b),
            lambda L, da, db: (dot(da, L[3:]) + dot(L[:3], db),),
            lambda L, g: (_scale(g[0], L[3:]), _scale(g[0], L[:3]))))
register(Op("cross", ("vec3", "vec3"), "vec3", cross, lambda a, b, o: tuple(a) + tuple(b),
            lambda L, da, db: vadd(cross(da, L[3:]), cross(L[:3], db)),
            lambda L, g: (cross(L[3:], g), cross(g, L[:3]))))
register(Op("matmul", ("mat3", "mat3"), "mat3", matmul, lambda a, b, o: tuple(a) + tuple(b),
            lambda L, da, db: vadd(matmul(da, L[9:]), matmul(L[:9], db)),
            lambda L, g: (matmul(g, transpose(L[9:])), matmul(transpose(L[:9]), g))))
register(Op("matvec", ("mat3", "vec3"), "vec3", matvec, lambda a, v, o: tuple(a) + tuple(v),
            lambda L, da, dv: vadd(matvec(da, L[9:]), matvec(L[:9], dv)),
            lambda L, g: (tuple(g[i] * L[9 + j] for i in range(3) for j in range(3)), matvec(transpose(L[:9]), g))))

# rotation chaining, eq. 3.1-3.3: the linearizer stores the first quaternion
register(Op("qmul", ("quat", "quat"), "quat", qmul, lambda a, b, o: tuple(a),
            lambda L, da, db: vadd(da, qrot(L, db)), lambda L, g: (g, qrot_conj(L, g))))
# rotating a vector: d(q v q*) = dq x (q v q*) + q dv q*
register(Op("rotate", ("quat", "vec3"), "vec3", qrot, lambda q, v, o: tuple(q) + tuple(o),
            lambda L, dq, dv: vadd(cross(dq, L[4:]), qrot(L[:4], dv)),
            lambda L, g: (cross(L[4:], g), qrot_conj(L[:4], g))))
# (exp(v) q)* = q* exp(-v) = exp(-q* v q) q*
register(Op("conj", ("quat",), "quat", lambda q: (q[0], -q[1], -q[2], -q[3]), lambda q, o: tuple(q),
            lambda L, dq: _neg(qrot_conj(L, dq)), lambda L, g: (_neg(qrot(L, g)),)))


# rotation matrices with rotation-vector gradients: chaining stores the first matrix
register(Op("rmul", ("rot3", "rot3"), "rot3", matmul, lambda a, b, o: tuple(a),
            lambda L, da, db: vadd(da, matvec(L, db)), lambda L, g: (g, matvec(transpose(L), g))))
register(Op("rrotate", ("rot3", "vec3"), "vec3", matvec, lambda r, v, o: tuple(r) + tuple(o),
            lambda L, dr, dv: vadd(cross(dr, L[9:]), matvec(L[:9], dv)),
            lambda L, g: (cross(L[9:], g), matvec(transpose(L[:9]), g))))
# a quaternion and its matrix share the rotation-vector gradient: both rules are moves
register(Op("to_matrix", ("quat",), "rot3", quat_to_matrix, lambda q, o: (), lambda L, dq: dq, lambda L, g: (g,)))


def angle_axis_op(axis: tuple[float, float, float]) -> Op:
    """Rotation by a traced angle about a constant unit axis, eq. 3.4-3.5: the forward rule
    is a scalar-vector product, the reverse a dot product; no trigonometry in either."""
    name = "angle_axis[{:.17g},{:.17g},{:.17g}]".format(*axis)
    if name not in OPS:
        ax = tuple(float(a) for a in axis)

        def ev(t: Comps) -> Comps:
            h = 0.5 * t[0]
            s = S.sin(h)
            return (S.cos(h), s * ax[0], s * ax[1], s * ax[2])

        register(Op(name, ("scalar",), "quat", ev, lambda t, o: (),
                    lambda L, dt: _scale(dt[0], ax), lambda L, g: ((dot(g, ax),),)))
    return OPS[name]


def plain_rules(op: Op) -> Op:
    """Forward and reverse rules of an operator without a linearizer: the framework's scalar
    AD of its eval, inlined on the stored arguments (the plain rule)."""
    counters["plain_rule"] += 1
    if op.name not in _warned:
        _warned.add(op.name)
        log.warning("autolin: operator %r has no linearizer; using the plain rule (scalar AD on its arguments)",
                    op.name)
    sizes = [SIZE[t] for t in op.arg_types]
    names = [f"a{k}_{c}" for k, n in enumerate(sizes) for c in range(n)]

    def flat(*xs: Any) -> list[Any]:
        parts, i = [], 0
        for n in sizes:
            parts.append(tuple(xs[i:i + n]))
            i += n
        return list(op.eval(*parts))

    p = S.trace_scalar(flat, names)
    jp, vp = S.jvp_program(p), S.vjp_program(p)

    def split(flat_vals: list[Any]) -> tuple[Comps, ...]:
        out, i = [], 0
        for n in sizes:
            out.append(tuple(flat_vals[i:i + n]))
            i += n
        return tuple(out)

    def fwd(L: Comps, *d: Comps) -> Comps:
        b = L[0].b if isinstance(L[0], S.Sym) else None
        return tuple(S.replay(jp, list(L) + [x for v in d for x in v], builder=b))

    def rev(L: Comps, g: Comps) -> tuple[Comps, ...]:
        b = L[0].b if isinstance(L[0], S.Sym) else None
        return split(S.replay(vp, list(L) + list(g), builder=b))

    return Op(op.name, op.arg_types, op.out_type, op.eval, lambda *a: tuple(x for v in a[:-1] for x in v), fwd, rev)


def rules(name: str) -> Op:
    op = OPS[name]
    return op if op.lin is not None else plain_rules(op)
