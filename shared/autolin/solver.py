"""Gauss-Newton with a conjugate-gradient inner loop, matrix-free through the generated
programs (the use of thesis sections 2.9 and 3.2): each outer step linearizes the residuals
once, then CG applies J^T J v + lambda v only through the forward and reverse programs
(multiplies and adds); steps are added with the accumulation programs, so quaternion
parameters take rotation-vector steps.

Residuals are a batch of one traced function: observation k reads parameter block
`index[j][k]` of each parameter array j, plus per-observation constant data.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import ops as O
from .programs import Linearized, compile


@dataclass
class SolveResult:
    params: list[np.ndarray]
    cost: float                      # 0.5 * sum of squared residuals
    iterations: int
    cg_iterations: int
    costs: list[float] = field(default_factory=list)


class LeastSquares:
    """min over parameter blocks of 0.5 sum_k |fn(params[index][k], data[k])|^2."""

    def __init__(self, fn: Callable[..., Any], param_types: Sequence[str], data_types: Sequence[str],
                 index: Sequence[np.ndarray]) -> None:
        self.param_types = list(param_types)
        self.n_data = len(data_types)
        self.index = [np.asarray(i, dtype=np.intp) for i in index]
        if len(self.index) != len(self.param_types):
            raise ValueError("one index array per parameter array")
        self.f: Linearized = compile(fn, list(param_types) + list(data_types))
        self._acc = {t: compile(lambda x: x, [t]) for t in set(param_types)}  # x (+) dx per type

    def _gather(self, params: Sequence[np.ndarray], data: Sequence[np.ndarray]) -> list[np.ndarray]:
        return [p[i] for p, i in zip(params, self.index, strict=True)] + list(data)

    def residuals(self, params: Sequence[np.ndarray], data: Sequence[np.ndarray]) -> tuple[list[np.ndarray], list]:
        return self.f.linearize(*self._gather(params, data))

    def _jv(self, L: list, v: Sequence[np.ndarray], data: Sequence[np.ndarray]) -> list[np.ndarray]:
        dx = [x[i] for x, i in zip(v, self.index, strict=True)] + [np.zeros_like(d) for d in data]
        return self.f.forward(L, *dx)

    def _jtw(self, L: list, w: Sequence[np.ndarray], shapes: list[tuple[int, ...]]) -> list[np.ndarray]:
        g = self.f.reverse(L, *w)
        out = []
        for gj, i, s in zip(g, self.index, shapes, strict=False):
            acc = np.zeros(s)
            np.add.at(acc, i, gj)  # observations sharing a block sum their gradients
            out.append(acc)
        return out

    def solve(self, params: Sequence[np.ndarray], data: Sequence[np.ndarray], *, iterations: int = 30,
              cg_iterations: int = 50, damping: float = 1e-4, tol: float = 1e-12,
              fixed: Sequence[np.ndarray] | None = None) -> SolveResult:
        """Levenberg-style damped Gauss-Newton; `fixed[j]` is a boolean mask of blocks of
        parameter array j held constant (e.g. the gauge)."""
        params = [np.array(p, dtype=float) for p in params]
        shapes = [p.shape[:1] + _grad_shape(t) for p, t in zip(params, self.param_types, strict=True)]
        masks = [np.ones(s[0], bool) if fixed is None or fixed[j] is None else ~np.asarray(fixed[j])
                 for j, s in enumerate(shapes)]
        r, L = self.residuals(params, data)
        cost = 0.5 * sum(float(np.sum(x * x)) for x in r)
        res = SolveResult(params, cost, 0, 0, [cost])
        lam = damping
        for it in range(iterations):
            g = [gj * _bcast(m, gj) for gj, m in zip(self._jtw(L, r, shapes), masks, strict=True)]
            if sum(float(np.sum(x * x)) for x in g) < tol ** 2:
                break

            def hv(v: list[np.ndarray], L: list = L, lam: float = lam) -> list[np.ndarray]:
                jv = self._jv(L, v, data)
                out = self._jtw(L, jv, shapes)
                return [(o + lam * x) * _bcast(m, x) for o, x, m in zip(out, v, masks, strict=True)]

            step, n_cg = _cg(hv, [-x for x in g], cg_iterations)
            res.cg_iterations += n_cg
            cand = [self._acc[t].accumulate([p], [s])[0] for p, s, t in zip(params, step, self.param_types,
                                                                              strict=True)]
            r2, L2 = self.residuals(cand, data)
            c2 = 0.5 * sum(float(np.sum(x * x)) for x in r2)
            res.iterations = it + 1
            if c2 < cost:
                params, r, L, lam = cand, r2, L2, max(lam / 3, 1e-12)
                done = cost - c2 <= tol * max(cost, 1.0)
                cost = c2
                res.costs.append(cost)
                if done:
                    break
            else:
                lam *= 4
        res.params, res.cost = params, cost
        return res


def _grad_shape(t: str) -> tuple[int, ...]:
    return {"scalar": (), "vec3": (3,), "mat3": (3, 3)}[O.GRAD[t]]


def _bcast(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    return m.reshape(m.shape + (1,) * (x.ndim - 1))


def _dot(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    return sum(float(np.sum(x * y)) for x, y in zip(a, b, strict=True))


def _cg(hv: Callable[[list[np.ndarray]], list[np.ndarray]], b: list[np.ndarray], iters: int,
        rtol: float = 1e-10) -> tuple[list[np.ndarray], int]:
    """Conjugate gradients on H x = b with H given only as a product."""
    x = [np.zeros_like(v) for v in b]
    r = [v.copy() for v in b]
    p = [v.copy() for v in b]
    rr = _dot(r, r)
    stop = rtol * rtol * rr
    k = 0
    while k < iters:
        k += 1
        hp = hv(p)
        php = _dot(p, hp)
        if php <= 0:
            break
        a = rr / php
        x = [xi + a * pi for xi, pi in zip(x, p, strict=True)]
        r = [ri - a * hi for ri, hi in zip(r, hp, strict=True)]
        rr2 = _dot(r, r)
        if rr2 <= stop:
            break
        p = [ri + (rr2 / rr) * pi for ri, pi in zip(r, p, strict=True)]
        rr = rr2
    return x, k
