"""Optimizers on the residual objective: matrix-free Gauss-Newton with a conjugate-gradient inner
loop and diagonal regularization (thesis 2.9), and the SGD / Adam baselines.

Gauss-Newton: at each outer iteration the residual r(w) of a fresh batch is linearized around w;
CG solves (J^T J + lambda I) dw = -J^T r using only products J^T u (reverse mode on the recorded
rollout) and J v (reverse mode through the graph of u -> J^T u, which is linear in u: the
double-backward form of forward mode), never forming J and never re-running the rollout inside CG. lambda adapts
as in Levenberg-Marquardt: an accepted step lowers it, a rejected one (higher loss or a
non-finite rollout) raises it and solves again.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

ResidualFn = Callable[[torch.Tensor], torch.Tensor]


@dataclass
class GaussNewton:
    lam: float = 1e-2           # diagonal regularization, adapted
    cg_iters: int = 10
    cg_tol: float = 1e-3        # relative residual of the inner solve
    max_tries: int = 4
    lam_min: float = 1e-6
    lam_max: float = 1e6
    counters: dict[str, int] = field(default_factory=lambda: {"rejected": 0, "nonfinite": 0, "cg_iters": 0})

    def step(self, fn: ResidualFn, w: torch.Tensor) -> tuple[torch.Tensor, float]:
        """One outer iteration on the batch of `fn`: the new parameters and their loss."""
        w = w.detach()
        wg = w.clone().requires_grad_(True)
        r = fn(wg)
        loss0 = float((r @ r).detach())
        if not torch.isfinite(r).all():
            self.counters["nonfinite"] += 1
            return w, float("nan")
        u = torch.zeros_like(r, requires_grad=True)
        jt_u = torch.autograd.grad(r, wg, u, create_graph=True)[0]  # J^T u, linear in u

        def jt(x: torch.Tensor) -> torch.Tensor:
            return torch.autograd.grad(r, wg, x, retain_graph=True)[0]

        def j(v: torch.Tensor) -> torch.Tensor:
            return torch.autograd.grad(jt_u, u, v, retain_graph=True)[0]
        g = jt(r.detach())
        for _ in range(self.max_tries):
            lam = self.lam

            def apply(v: torch.Tensor, lam: float = lam) -> torch.Tensor:
                return jt(j(v)) + lam * v
            dw = self.cg(apply, -g)
            with torch.no_grad():
                r1 = fn(w + dw)
            loss1 = float(r1 @ r1)
            if torch.isfinite(r1).all() and loss1 < loss0:
                self.lam = max(self.lam / 3.0, self.lam_min)
                return w + dw, loss1
            self.counters["nonfinite" if not torch.isfinite(r1).all() else "rejected"] += 1
            self.lam = min(self.lam * 4.0, self.lam_max)
        return w, loss0

    def cg(self, apply: Callable[[torch.Tensor], torch.Tensor], b: torch.Tensor) -> torch.Tensor:
        """Conjugate gradients on apply(x) = b from x = 0."""
        x = torch.zeros_like(b)
        res = b.clone()
        p = res.clone()
        rr = float(res @ res)
        stop = self.cg_tol ** 2 * rr
        for _ in range(self.cg_iters):
            if rr == 0.0:  # already solved (a zero gradient)
                break
            ap = apply(p)
            curvature = float(p @ ap)
            if not curvature > 0.0:  # lambda > 0 keeps the system positive definite; guard NaN
                break
            alpha = rr / curvature
            x = x + alpha * p
            res = res - alpha * ap
            rr_new = float(res @ res)
            self.counters["cg_iters"] += 1
            if rr_new <= stop:
                break
            p = res + (rr_new / rr) * p
            rr = rr_new
        return x


@dataclass
class FirstOrder:
    """SGD or Adam on loss = |r|^2; a non-finite loss or gradient skips the step (counted) and
    halves the learning rate."""
    kind: str
    lr: float
    counters: dict[str, int] = field(default_factory=lambda: {"nonfinite": 0})
    _state: torch.optim.Optimizer | None = None
    _param: torch.Tensor | None = None

    def step(self, fn: ResidualFn, w: torch.Tensor) -> tuple[torch.Tensor, float]:
        if self._param is None:
            self._param = w.detach().clone().requires_grad_(True)
            opt = {"sgd": torch.optim.SGD, "adam": torch.optim.Adam}
            if self.kind not in opt:
                raise ValueError(f"unknown optimizer {self.kind!r}; optimizers: gn, sgd, adam")
            self._state = opt[self.kind]([self._param], lr=self.lr)
        assert self._state is not None
        self._state.zero_grad()
        r = fn(self._param)
        loss = r @ r
        loss.backward()
        if not (torch.isfinite(loss) and torch.isfinite(self._param.grad).all()):
            self.counters["nonfinite"] += 1
            for group in self._state.param_groups:
                group["lr"] *= 0.5
            return self._param.detach().clone(), float("nan")
        self._state.step()
        return self._param.detach().clone(), float(loss)
