"""The five-frame chain of the validation suite and the bench written directly in torch: the
scalar-AD reference (torch.func jvp/vjp) autolin's programs are checked and timed against. Imports
torch, so only the tests and bench/autolin.py load it."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

from shared.autolin import ops as O


def qmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of (..., 4) quaternions (w, x, y, z)."""
    return torch.stack(O.qmul(a.unbind(-1), b.unbind(-1)), -1)


def rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """q v q* for unit quaternions (..., 4) and vectors (..., 3)."""
    conj = torch.tensor([1.0, -1, -1, -1], dtype=q.dtype)
    vq = torch.cat([torch.zeros_like(v[..., :1]), v], -1)
    return qmul(qmul(q, vq), q * conj)[..., 1:]


def five_frame_chain(axes: Sequence[Sequence[float]]) -> Callable[..., tuple[torch.Tensor, torch.Tensor]]:
    """f(q0..q4, t0..t4, theta0..theta4, p) -> (orientation, position) of point p after five frames,
    frame k rotating by theta_k about ``axes[k]`` after its own rotation q_k and offset t_k."""
    ax = torch.tensor(axes, dtype=torch.float64)

    def chain(*a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        qs, ts, th, p = a[0:5], a[5:10], a[10:15], a[15]

        def joint(k: int) -> torch.Tensor:
            h = th[k][..., None] / 2
            return qmul(qs[k], torch.cat([torch.cos(h), torch.sin(h) * ax[k]], -1))

        q, t = joint(0), ts[0]
        for k in range(1, 5):
            t = t + rotate(q, ts[k])
            q = qmul(q, joint(k))
        return q, t + rotate(q, p)

    return chain
