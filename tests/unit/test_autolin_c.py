"""autolin's plain-C emission: the compiled programs compute what the numpy plans compute."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

import shared.autolin as al
from shared.autolin.emit_c import CProgram, c_source

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")


def test_c_source_keeps_the_counted_instructions():
    f = al.compile(lambda a, b: a * b, ["quat", "quat"])
    src = c_source(f.scalar["forward"], "qchain_fwd")
    body = [ln for ln in src.splitlines() if " = r" in ln and ("+" in ln or "-" in ln or "*" in ln)]
    assert len(body) == 33
    with pytest.raises(ValueError, match="identifier"):
        c_source(f.scalar["forward"], "bad name")


def test_compiled_programs_match_numpy():
    f = al.compile(lambda q, v, t: (q * q.conj()) * al.angle_axis(t, [0, 1.0, 0]) * v + al.sin(t) * v,
                   ["quat", "vec3", "scalar"])
    rng = np.random.default_rng(2)
    for name in ("linearize", "forward", "reverse", "accumulate"):
        p = f.scalar[name]
        xs = [rng.normal(size=50) for _ in p.inputs]
        got = CProgram(p, f"al_{name}")(xs)
        for g, w in zip(got, f.exe[name](xs), strict=True):
            np.testing.assert_allclose(g, np.broadcast_to(w, (50,)), rtol=1e-13, atol=1e-15)


def test_linearized_runs_in_c():
    f = al.compile(lambda a, b, v: (a * b) * v, ["quat", "quat", "vec3"])
    c = f.with_c()
    rng = np.random.default_rng(4)
    q = rng.normal(size=(2, 8, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    v, d1, d2, d3, w = (rng.normal(size=(8, 3)) for _ in range(5))
    (y,), L = f.linearize(q[0], q[1], v)
    (yc,), Lc = c.linearize(q[0], q[1], v)
    np.testing.assert_allclose(yc, y, rtol=1e-14)
    np.testing.assert_allclose(c.forward(Lc, d1, d2, d3)[0], f.forward(L, d1, d2, d3)[0], rtol=1e-13)
    for g, h in zip(c.reverse(Lc, w), f.reverse(L, w), strict=True):
        np.testing.assert_allclose(g, h, rtol=1e-13)
