"""How the optimizer calls CasADi (pure): buffered calls on preallocated numpy arrays, and the QP
solver options it uses. Split from optimizer.py so the optimizer reads as the problem it solves."""

from __future__ import annotations

import casadi as ca
import numpy as np


def qp_options(name: str) -> dict:
    """Quiet, non-throwing options per CasADi conic plugin (the ones compared in docs/trajopt.md)."""
    common = {"error_on_fail": False}
    specific = {
        "ipqp": {"print_iter": False, "print_header": False, "print_info": False, "constr_viol_tol": 1e-6,
                 "dual_inf_tol": 1e-6},
        "qrqp": {"print_iter": False, "print_header": False, "print_info": False},
        "osqp": {"osqp": {"verbose": False, "eps_abs": 1e-7, "eps_rel": 1e-7, "polish": True, "max_iter": 20000},
                 "warm_start_primal": True, "warm_start_dual": True},
        "hpipm": {"hpipm": {"mode": "robust"}},
        "daqp": {},
        "proxqp": {},
        "highs": {"highs": {"output_flag": False}},
    }
    return {**common, **specific.get(name, {})}


class BufferedFunction:
    """A CasADi function called through its buffer interface: inputs and outputs are preallocated
    nonzero vectors (numpy arrays the function reads and writes in place). An ordinary call
    converts every argument to a DM and every output back, about 0.25 ms per call of the SQP
    function here, more than evaluating it. ``args`` and ``res`` may be re-pointed (``bind_arg``,
    ``bind_res``) at another function's arrays, so one function's output feeds the next one's input
    without a copy."""

    def __init__(self, f: ca.Function) -> None:
        self.f = f
        self.args = [np.zeros(f.nnz_in(i)) for i in range(f.n_in())]
        self.res = [np.zeros(f.nnz_out(i)) for i in range(f.n_out())]
        self._buf, self._eval = f.buffer()  # the buffer holds raw pointers: the arrays live in self
        for i, a in enumerate(self.args):
            self._buf.set_arg(i, memoryview(a))
        for i, r in enumerate(self.res):
            self._buf.set_res(i, memoryview(r))

    def bind_arg(self, i: int, array: np.ndarray) -> None:
        assert array.dtype == np.float64 and array.flags.c_contiguous and array.size == self.f.nnz_in(i)
        self.args[i] = array
        self._buf.set_arg(i, memoryview(array))

    def bind_res(self, i: int, array: np.ndarray) -> None:
        assert array.dtype == np.float64 and array.flags.c_contiguous and array.size == self.f.nnz_out(i)
        self.res[i] = array
        self._buf.set_res(i, memoryview(array))

    def __call__(self, *args) -> list[np.ndarray]:
        """Copy the given inputs (dense values or nonzeros, in input order; None keeps what the
        input array holds), evaluate, and return the output arrays (overwritten by the next call)."""
        for dst, src in zip(self.args, args, strict=False):
            if src is not None:
                dst[...] = src
        self._eval()
        return self.res

    def stats(self) -> dict:
        return self._buf.stats()


class OrdinaryCall(BufferedFunction):
    """The same interface, evaluated by an ordinary call (DM in, DM out): for QP plugins that
    misbehave across buffered calls (HPIPM's stage-wise QPs fail from the second solve on)."""

    def __call__(self, *args) -> list[np.ndarray]:
        for dst, src in zip(self.args, args, strict=False):
            if src is not None:
                dst[...] = src
        out = self.f(*[ca.DM(self.f.sparsity_in(i), a) for i, a in enumerate(self.args)])
        for dst, r in zip(self.res, out, strict=True):
            dst[...] = np.asarray(ca.DM(r).nonzeros())
        return self.res

    def stats(self) -> dict:
        return self.f.stats()


BUFFERED_QP = ("ipqp",)  # plugins checked to give the ordinary call's results through buffers
