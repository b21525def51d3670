"""Gauss-Newton with a conjugate-gradient inner loop, matrix-free through the generated
programs (the use of thesis sections 2.9 and 3.2): each outer step linearizes the residuals
once, then CG applies J^T J v + lambda D v only through the forward and reverse programs
(multiplies and adds). D is diag(J^T J) (Marquardt's diagonal regularization, which makes the
damping independent of each parameter's units) or the identity. Steps are added with the
accumulation programs, so quaternion parameters take rotation-vector steps.

Residuals are a batch of one traced function: observation k reads parameter block
`index[j][k]` of each parameter array j, plus per-observation constant data. Parameter arrays
read through equal index arrays form a group of entities (e.g. a camera's pose and intrinsics).
An observation reads one entity per group, so H = J^T J restricted to one group is block
diagonal: the group with the most entities (points, board poses) is eliminated exactly through
its small blocks and CG runs on the Schur complement of the others (an implicit Schur
complement: each product is two H products), preconditioned with that complement's diagonal
blocks (Schur-Jacobi, matrix-free beyond per-entity blocks) or with the complete complement,
formed densely and factored once per step (then CG converges in about one iteration: a direct
Schur solve). The default takes the complete complement when the kept group is small (a few
cameras), where it is much faster, and Schur-Jacobi otherwise. All blocks come from one reverse
pass per residual component, which gives each observation's rows of J.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import ops as O
from .programs import Linearized, compile

# the "auto" preconditioner factors the complete Schur complement up to this many kept unknowns
# (a dense Cholesky-sized inverse of at most 1000 x 1000 per step costs less than a few CG products)
COMPLETE_SCHUR_MAX = 1000
Vec = list[np.ndarray]  # one array per parameter array, shaped like its gradients


@dataclass
class SolveResult:
    params: list[np.ndarray]
    cost: float                      # 0.5 * sum of squared residuals
    iterations: int
    cg_iterations: int
    costs: list[float] = field(default_factory=list)   # after each accepted step, the start first
    times: list[float] = field(default_factory=list)   # seconds from the start of solve() to each cost
    cpu_times: list[float] = field(default_factory=list)  # the same in process CPU seconds


@dataclass
class _Blocks:
    diag: list[np.ndarray]           # per group: (entities, D, D) blocks of J^T J
    cross: list[np.ndarray | None]   # per group other than the eliminated one: (pairs, D, De)


class LeastSquares:
    """min over parameter blocks of 0.5 sum_k |fn(params[index][k], data[k])|^2."""

    def __init__(self, fn: Callable[..., Any], param_types: Sequence[str], data_types: Sequence[str],
                 index: Sequence[np.ndarray], backend: str = "numpy") -> None:
        """`backend`: "numpy" (the register plan) or "c" (the programs compiled to C, emit_c)."""
        self.param_types = list(param_types)
        self.n_data = len(data_types)
        self.index = [np.asarray(i, dtype=np.intp) for i in index]
        if len(self.index) != len(self.param_types):
            raise ValueError("one index array per parameter array")
        if backend not in ("numpy", "c"):
            raise ValueError(f"backend must be 'numpy' or 'c', got {backend!r}")
        self.f: Linearized = compile(fn, list(param_types) + list(data_types))
        if backend == "c":
            self.f = self.f.with_c()
        self._acc = {t: compile(lambda x: x, [t]) for t in set(param_types)}  # x (+) dx per type
        self.groups: list[list[int]] = []
        for j, i in enumerate(self.index):
            g = next((g for g in self.groups if np.array_equal(self.index[g[0]], i)), None)
            if g is None:
                self.groups.append([j])
            else:
                g.append(j)
        sizes = [int(self.index[g[0]].max(initial=-1)) + 1 for g in self.groups]
        self.elim = int(np.argmax(sizes)) if len(self.groups) > 1 else None
        # per other group: (entity, eliminated entity) pairs that observations touch
        self._pairs: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = []
        for k, g in enumerate(self.groups):
            if self.elim is None or k == self.elim:
                self._pairs.append(None)
                continue
            key = self.index[g[0]] * sizes[self.elim] + self.index[self.groups[self.elim][0]]
            uniq, inverse = np.unique(key, return_inverse=True)
            self._pairs.append((inverse, uniq // sizes[self.elim], uniq % sizes[self.elim]))

    def _gather(self, params: Sequence[np.ndarray], data: Sequence[np.ndarray]) -> list[np.ndarray]:
        return [p[i] for p, i in zip(params, self.index, strict=True)] + list(data)

    def residuals(self, params: Sequence[np.ndarray], data: Sequence[np.ndarray]) -> tuple[list[np.ndarray], list]:
        return self.f.linearize(*self._gather(params, data))

    def _jv(self, L: list, v: Sequence[np.ndarray], data: Sequence[np.ndarray]) -> list[np.ndarray]:
        dx = [x[i] for x, i in zip(v, self.index, strict=True)] + [np.zeros_like(d) for d in data]
        return self.f.forward(L, *dx)

    def _jtw(self, L: list, w: Sequence[np.ndarray], shapes: list[tuple[int, ...]]) -> Vec:
        g = self.f.reverse(L, *w)
        return [_scatter(gj, i, s) for gj, i, s in zip(g, self.index, shapes, strict=False)]

    def _blocks(self, L: list, shapes: list[tuple[int, ...]]) -> _Blocks:
        batch = self.index[0].shape  # one residual per observation
        gtypes = [O.GRAD[t] for t in self.f.out_types]
        zero = [np.zeros(batch + _grad_shape(t)) for t in gtypes]
        dims = [sum(int(np.prod(shapes[j][1:])) for j in g) for g in self.groups]
        diag = [np.zeros((shapes[g[0]][0], d, d)) for g, d in zip(self.groups, dims, strict=True)]
        cross = [None if p is None else np.zeros((len(p[1]), d, dims[self.elim]))  # type: ignore[index]
                 for p, d in zip(self._pairs, dims, strict=True)]
        for j, t in enumerate(gtypes):
            for c in range(O.SIZE[t]):
                w = [z.copy() for z in zero]
                w[j].reshape(batch + (-1,))[..., c] = 1.0
                g = self.f.reverse(L, *w)  # this residual component's row of J, per observation
                rows = [np.concatenate([g[k].reshape(batch + (-1,)) for k in grp], axis=-1) for grp in self.groups]
                for acc, r, grp in zip(diag, rows, self.groups, strict=True):
                    acc += _segment_sum(r[..., :, None] * r[..., None, :], self.index[grp[0]], len(acc))
                for acc, r, p in zip(cross, rows, self._pairs, strict=True):
                    if p is not None:
                        acc += _segment_sum(r[..., :, None] * rows[self.elim][..., None, :], p[0], len(acc))
        return _Blocks(diag, cross)

    def jtj_blocks(self, L: list, shapes: list[tuple[int, ...]]) -> list[np.ndarray]:
        """Per group of `self.groups`, the (entities, D, D) diagonal blocks of J^T J, D the summed
        gradient sizes of the group's arrays."""
        return self._blocks(L, shapes).diag

    def jtj_diagonal(self, L: list, shapes: list[tuple[int, ...]]) -> Vec:
        """diag(J^T J) per parameter array, shaped like its gradients."""
        return self._split([np.diagonal(b, axis1=1, axis2=2) for b in self.jtj_blocks(L, shapes)], shapes)

    def _flat(self, v: Sequence[np.ndarray]) -> list[np.ndarray]:
        return [np.concatenate([v[j].reshape(len(v[j]), -1) for j in g], axis=1) for g in self.groups]

    def _split(self, flat: list[np.ndarray], shapes: list[tuple[int, ...]]) -> Vec:
        out: Vec = [np.empty(0)] * len(shapes)
        for f, g in zip(flat, self.groups, strict=True):
            k = 0
            for j in g:
                d = int(np.prod(shapes[j][1:]))
                out[j] = f[:, k:k + d].reshape(shapes[j])
                k += d
        return out

    def _apply(self, inv: list[np.ndarray], v: Vec, shapes: list[tuple[int, ...]], groups: Sequence[int]) -> Vec:
        """The block matrices `inv` of `groups` applied to v; other groups' entries zero."""
        flat = self._flat(v)
        out = [np.zeros_like(f) if k not in groups else np.einsum("nij,nj->ni", inv[k], f) if inv[k].ndim == 3
               else (inv[k] @ f.reshape(-1)).reshape(f.shape) for k, f in enumerate(flat)]
        return self._split(out, shapes)

    def _complete_schur(self, b: _Blocks, damped: list[np.ndarray], inv_e: np.ndarray, free: list[np.ndarray]
                        ) -> np.ndarray:
        """The complete Schur complement of the one kept group, dense (entities * D square):
        its damped diagonal blocks minus H_ib H_bb^-1 H_bj over every pair of kept entities i, j
        that meet an eliminated entity b."""
        k = next(i for i in range(len(self.groups)) if i != self.elim)
        ent, elim = self._pairs[k][1], self._pairs[k][2]  # type: ignore[index]
        c = b.cross[k] * (free[k][ent][:, :, None] & free[self.elim][elim][:, None, :])  # type: ignore[index]
        order = np.argsort(elim, kind="stable")
        starts = np.flatnonzero(np.r_[True, np.diff(elim[order]) != 0])
        sizes = np.diff(np.r_[starts, len(order)])
        # all pairs (p, q) of pairs that share their eliminated entity
        p1 = np.concatenate([np.repeat(order[s:s + n], n) for s, n in zip(starts, sizes, strict=True)])
        p2 = np.concatenate([np.tile(order[s:s + n], n) for s, n in zip(starts, sizes, strict=True)])
        m = (c[p1] @ inv_e[elim[p1]]) @ c[p2].transpose(0, 2, 1)
        n, d = damped[k].shape[:2]
        s4 = np.zeros((n, n, d, d))
        s4[np.arange(n), np.arange(n)] = damped[k]
        s4 -= _segment_sum(m, ent[p1] * n + ent[p2], n * n).reshape(n, n, d, d)
        return s4.transpose(0, 2, 1, 3).reshape(n * d, n * d)

    def _preconditioner(self, b: _Blocks, dmp: list[np.ndarray], lam: float, free: list[np.ndarray],
                        complete: bool = False) -> list:
        """Inverses of the damped diagonal blocks of H, except for the groups kept by the Schur
        complement: there the inverses of the complement's diagonal blocks,
        H_ii - sum_b H_ib H_bb^-1 H_bi over the eliminated entities b that entity i meets."""
        damped = [_damped(d, m, lam, f) for d, m, f in zip(b.diag, dmp, free, strict=True)]
        if self.elim is None:
            return [np.linalg.inv(a) for a in damped]
        e = self.elim
        inv_e = np.linalg.inv(damped[e]) * _outer(free[e])
        if complete:
            k = next(i for i in range(len(self.groups)) if i != e)
            s = self._complete_schur(b, damped, inv_e, free)
            fk = free[k].reshape(-1)
            out = [inv_e, inv_e]
            out[k] = np.linalg.inv(s) * (fk[:, None] & fk[None, :])  # dense: applied to the whole group
            return out
        out = []
        for k, (a, c, p) in enumerate(zip(damped, b.cross, self._pairs, strict=True)):
            if k == e or c is None or p is None:
                out.append(inv_e if k == e else np.linalg.inv(a))
                continue
            cm = c * (free[k][p[1]][:, :, None] & free[e][p[2]][:, None, :])
            s = a.copy()
            s -= _segment_sum((cm @ inv_e[p[2]]) @ cm.transpose(0, 2, 1), p[1], len(s))
            out.append(np.linalg.inv(s) * _outer(free[k]))
        return out

    def _step(self, hv: Callable[[Vec], Vec], b: Vec, inv: list[np.ndarray], shapes: list[tuple[int, ...]],
              iters: int, rtol: float) -> tuple[Vec, int]:
        """Solves H x = b: CG on the Schur complement of the eliminated group, then its part by
        back-substitution through its block inverses."""
        rest = [k for k in range(len(self.groups)) if k != self.elim]
        if self.elim is None:
            return _cg(hv, b, iters, lambda v: self._apply(inv, v, shapes, rest), rtol)
        e = self.elim
        ej = set(self.groups[e])

        def only(v: Vec, elim: bool) -> Vec:
            return [x if (j in ej) == elim else np.zeros_like(x) for j, x in enumerate(v)]

        def schur(vc: Vec) -> Vec:
            h = hv(vc)
            wb = self._apply(inv, h, shapes, [e])
            return only([a - c for a, c in zip(h, hv(wb), strict=True)], False)

        wb = self._apply(inv, only(b, True), shapes, [e])
        bc = only([x - h for x, h in zip(b, hv(wb), strict=True)], False)
        xc, n = _cg(schur, bc, iters, lambda v: self._apply(inv, v, shapes, rest), rtol)
        xb = self._apply(inv, [x - h for x, h in zip(b, hv(xc), strict=True)], shapes, [e])
        return [c + d for c, d in zip(xc, xb, strict=True)], n

    def solve(self, params: Sequence[np.ndarray], data: Sequence[np.ndarray], *, iterations: int = 50,
              cg_iterations: int = 100, damping: float = 1e-4, tol: float = 1e-12,
              fixed: Sequence[np.ndarray | None] | None = None, regularization: str = "diagonal",
              preconditioner: str = "auto") -> SolveResult:
        """Damped Gauss-Newton: `regularization` "diagonal" (lambda diag(J^T J), Marquardt) or
        "identity" (lambda I, Levenberg); `fixed[j]` is a boolean mask of blocks of parameter
        array j held constant (e.g. the gauge). `preconditioner` "schur-jacobi" (the diagonal
        blocks of the Schur complement) or "schur" (the complete complement, dense, factored once
        per step: for problems whose kept group is small, e.g. a few cameras; needs exactly two
        groups), or "auto" (the default): "schur" when there are two groups and the kept one has at
        most `COMPLETE_SCHUR_MAX` unknowns, else "schur-jacobi"."""
        if regularization not in ("diagonal", "identity"):
            raise ValueError(f"regularization must be 'diagonal' or 'identity', got {regularization!r}")
        if preconditioner not in ("auto", "schur-jacobi", "schur"):
            raise ValueError(f"preconditioner must be 'auto', 'schur-jacobi' or 'schur', got {preconditioner!r}")
        if preconditioner == "schur" and len(self.groups) != 2:
            raise ValueError(f"the complete Schur preconditioner needs two groups of parameters, got {self.groups}")
        start, start_cpu = time.perf_counter(), time.process_time()
        params = [np.array(p, dtype=float) for p in params]
        shapes = [p.shape[:1] + _grad_shape(t) for p, t in zip(params, self.param_types, strict=True)]
        if preconditioner == "auto":
            kept = sum(int(np.prod(shapes[j])) for k, g in enumerate(self.groups) if k != self.elim for j in g)
            two = len(self.groups) == 2
            preconditioner = "schur" if two and kept <= COMPLETE_SCHUR_MAX else "schur-jacobi"
        masks = [np.ones(s, bool) if fixed is None or fixed[j] is None
                 else np.broadcast_to(_bcast(~np.asarray(fixed[j], bool), np.empty(s)), s).copy()
                 for j, s in enumerate(shapes)]
        free = self._flat(masks)
        r, L = self.residuals(params, data)
        cost = 0.5 * sum(float(np.sum(x * x)) for x in r)
        res = SolveResult(params, cost, 0, 0, [cost], [time.perf_counter() - start], [time.process_time() - start_cpu])
        lam, g0 = damping, 0.0
        blocks, blocks_of = _Blocks([], []), None
        dmp_flat: list[np.ndarray] = []
        for it in range(iterations):
            g = [gj * m for gj, m in zip(self._jtw(L, r, shapes), masks, strict=True)]
            gnorm = np.sqrt(_dot(g, g))
            g0 = g0 or gnorm
            if gnorm < tol:
                break
            if blocks_of is not L:  # a rejected step keeps the linearization and its blocks
                blocks, blocks_of = self._blocks(L, shapes), L
                if regularization == "diagonal":
                    diag = [np.diagonal(b, axis1=1, axis2=2) for b in blocks.diag]
                    # a column J does not touch still gets a little damping, so H stays positive definite
                    floor = 1e-12 * max(float(np.max(d)) for d in diag)
                    dmp_flat = [np.maximum(d, floor) for d in diag]
                else:
                    dmp_flat = [np.ones(b.shape[:2]) for b in blocks.diag]
            dmp = self._split(dmp_flat, shapes)
            inv = self._preconditioner(blocks, dmp_flat, lam, free, preconditioner == "schur")

            def hv(v: Vec, L: list = L, lam: float = lam, dmp: Vec = dmp) -> Vec:
                out = self._jtw(L, self._jv(L, v, data), shapes)
                return [(o + lam * d * x) * m for o, x, d, m in zip(out, v, dmp, masks, strict=True)]

            # inexact Newton: solve the step to a relative residual that shrinks with the gradient
            step, n_cg = self._step(hv, [-x for x in g], inv, shapes, cg_iterations, min(0.1, np.sqrt(gnorm / g0)))
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
                res.times.append(time.perf_counter() - start)
                res.cpu_times.append(time.process_time() - start_cpu)
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


def _dot(a: Vec, b: Vec) -> float:
    return sum(float(np.sum(x * y)) for x, y in zip(a, b, strict=True))


def _scatter(g: np.ndarray, i: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Sum of the rows of g into the blocks i reads (observations sharing a block add up)."""
    flat = g.reshape(len(g), -1)
    out = np.stack([np.bincount(i, weights=flat[:, c], minlength=shape[0]) for c in range(flat.shape[1])], axis=1)
    return out.reshape(shape)


def _segment_sum(x: np.ndarray, i: np.ndarray, n: int) -> np.ndarray:
    """(n, ...) sums of the rows of x by their index i (a sort and np.add.reduceat: add.at is slow)."""
    order = np.argsort(i, kind="stable")
    si = i[order]
    starts = np.flatnonzero(np.r_[True, si[1:] != si[:-1]])
    out = np.zeros((n,) + x.shape[1:])
    if len(si):
        out[si[starts]] = np.add.reduceat(x[order], starts, axis=0)
    return out


def _outer(f: np.ndarray) -> np.ndarray:
    return f[:, :, None] & f[:, None, :]


def _damped(b: np.ndarray, d: np.ndarray, lam: float, f: np.ndarray) -> np.ndarray:
    """b + lambda diag(d) on free entries; a fixed entry's row and column become the identity's."""
    a = b * _outer(f)
    idx = np.arange(a.shape[1])
    a[:, idx, idx] += np.where(f, lam * d, 1.0)
    return a


def _cg(hv: Callable[[Vec], Vec], b: Vec, iters: int, precond: Callable[[Vec], Vec], rtol: float) -> tuple[Vec, int]:
    """Preconditioned conjugate gradients on H x = b, H and the preconditioner given as products;
    stops when |H x - b| <= rtol |b|."""
    x = [np.zeros_like(v) for v in b]
    r = [v.copy() for v in b]
    z = precond(r)
    p = [v.copy() for v in z]
    rz = _dot(r, z)
    stop = rtol * rtol * _dot(r, r)
    k = 0
    while k < iters:
        k += 1
        hp = hv(p)
        php = _dot(p, hp)
        if php <= 0:
            break
        a = rz / php
        x = [xi + a * pi for xi, pi in zip(x, p, strict=True)]
        r = [ri - a * hi for ri, hi in zip(r, hp, strict=True)]
        if _dot(r, r) <= stop:
            break
        z = precond(r)
        rz2 = _dot(r, z)
        p = [zi + (rz2 / rz) * pi for zi, pi in zip(z, p, strict=True)]
        rz = rz2
    return x, k
