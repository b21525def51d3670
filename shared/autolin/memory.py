"""Static memory allocation and batched execution of scalar programs (thesis 3.2.5).

Each live value of a simplified scalar program gets a register; a register is reused as soon
as the last instruction reading its value has run, and the lowest free register is taken
first, so the register file stays compact (defragmented). The executable keeps that plan and
runs it on numpy arrays, one array per register over the batch.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .scalar import ScalarProgram

_FN: dict[str, Callable[..., Any]] = {"add": operator.add, "sub": operator.sub, "mul": operator.mul,
                                      "div": operator.truediv, "neg": operator.neg, "sin": np.sin,
                                      "cos": np.cos, "sqrt": np.sqrt}


def allocate(prog: ScalarProgram) -> tuple[dict[int, int], int]:
    """Register of every live node and the register count. Inputs and constants are written
    before the first instruction, so they take the first registers; an instruction's result
    takes the lowest register freed by values read for the last time."""
    live = prog.live()
    last: dict[int, int] = {}
    for i in live:
        for a in prog.nodes[i].args:
            last[a] = i
    for o in prog.outputs:
        last[o] = len(prog.nodes)  # outputs stay until the end
    pinned = [i for i in prog.inputs if i in last] + [i for i in live if prog.nodes[i].op in ("const", "zero")]
    reg = {i: k for k, i in enumerate(dict.fromkeys(pinned))}
    n_regs = len(reg)
    free: list[int] = []
    for i in live:
        if i in reg:
            continue
        for a in set(prog.nodes[i].args):
            if last.get(a) == i:
                free.append(reg[a])
        if free:
            free.sort()
            reg[i] = free.pop(0)
        else:
            reg[i], n_regs = n_regs, n_regs + 1
        if i not in last:  # computed but never read
            free.append(reg[i])
    return reg, n_regs


class Executable:
    """A scalar program with its registers assigned, run on numpy arrays."""

    def __init__(self, prog: ScalarProgram) -> None:
        self.prog = prog
        self.reg, self.n_regs = allocate(prog)
        live = set(prog.live())
        self.inputs = [self.reg.get(i, -1) for i in prog.inputs]
        self.consts = [(self.reg[i], prog.nodes[i].value) for i in sorted(live)
                       if prog.nodes[i].op in ("const", "zero")]
        self.steps = [(_FN[prog.nodes[i].op], self.reg[i], tuple(self.reg[a] for a in prog.nodes[i].args))
                      for i in sorted(live) if prog.nodes[i].op in _FN]
        self.outputs = [self.reg[o] for o in prog.outputs]

    def __call__(self, inputs: Sequence[Any]) -> list[Any]:
        r: list[Any] = [None] * self.n_regs
        for k, x in zip(self.inputs, inputs, strict=True):
            if k >= 0:
                r[k] = x
        for k, v in self.consts:
            r[k] = v
        with np.errstate(all="ignore"):  # non-finite results are reported by the caller
            for fn, o, a in self.steps:
                r[o] = fn(*[r[j] for j in a])
        return [r[k] for k in self.outputs]
