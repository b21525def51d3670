"""autolin's plain-C emission: the compiled programs compute what the numpy plans compute."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

import shared.autolin as al
from shared.autolin.chain import CHAIN_TYPES, chain
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




def random_args(types: list[str], batch: tuple[int, ...], rng: np.random.Generator) -> list[np.ndarray]:
    out = []
    for t in types:
        x = rng.normal(size=batch + al.ops.SHAPE[t])
        out.append(x / np.linalg.norm(x, axis=-1, keepdims=True) if t == "quat" else x)
    return out


@pytest.fixture(scope="module")
def chain_programs() -> tuple[al.Linearized, al.Linearized]:
    f = al.compile(chain, CHAIN_TYPES)
    return f, f.with_c()


@pytest.mark.parametrize("batch", [(1,), (7,), (2, 5)])
def test_chain_in_c_matches_numpy(batch: tuple[int, ...], chain_programs):
    """All four programs of the five-frame chain, C against the numpy plan, on random inputs;
    odd batches run the C programs' padded last group, a 2-D batch is flattened and restored."""
    f, c = chain_programs
    rng = np.random.default_rng(sum(batch))
    xs = random_args(CHAIN_TYPES, batch, rng)
    gtypes = [al.GRAD[t] for t in CHAIN_TYPES]
    ds = random_args(gtypes, batch, rng)
    w = random_args(["vec3", "vec3"], batch, rng)
    ys, L = f.linearize(*xs)
    yc, Lc = c.linearize(*xs)
    pairs = list(zip(yc, ys, strict=True))
    pairs += list(zip(c.forward(Lc, *ds), f.forward(L, *ds), strict=True))
    pairs += list(zip(c.reverse(Lc, *w), f.reverse(L, *w), strict=True))
    pairs += list(zip(c.forward(L, *ds), f.forward(L, *ds), strict=True))  # the numpy plan's data, repacked
    pairs += list(zip(c.accumulate(xs, ds), f.accumulate(xs, ds), strict=True))
    for got, want in pairs:
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    for a, b in zip(Lc.arrays(), L, strict=True):
        np.testing.assert_allclose(a, np.broadcast_to(b, batch), rtol=1e-12, atol=1e-12)


def test_rows_calls_match_typed_calls(chain_programs):
    f, c = chain_programs
    rng = np.random.default_rng(9)
    n = 33
    xs = random_args(CHAIN_TYPES, (n,), rng)
    ds = random_args([al.GRAD[t] for t in CHAIN_TYPES], (n,), rng)
    w = random_args(["vec3", "vec3"], (n,), rng)
    y, L = c.linearize_rows(np.concatenate([x.reshape(n, -1) for x in xs], axis=1))
    (q, t), _ = f.linearize(*xs)
    np.testing.assert_allclose(y, np.concatenate([q, t], axis=1), rtol=1e-12, atol=1e-12)
    jv = c.forward_rows(L, np.concatenate([d.reshape(n, -1) for d in ds], axis=1))
    np.testing.assert_allclose(jv, np.concatenate(c.forward(L, *ds), axis=1), rtol=0, atol=0)
    jtv = c.reverse_rows(L, np.concatenate(w, axis=1))
    np.testing.assert_allclose(jtv, np.concatenate([g.reshape(n, -1) for g in c.reverse(L, *w)], axis=1), rtol=0,
                               atol=0)
    buf = np.full_like(jtv, np.nan)
    assert c.reverse_rows(L, np.concatenate(w, axis=1), buf) is buf
    np.testing.assert_array_equal(buf, jtv)
    with pytest.raises(ValueError, match="C-contiguous float64"):
        c.forward_rows(L, np.zeros((n, 3)))
    with pytest.raises(ValueError, match="C-contiguous float64"):
        c.reverse_rows(L, np.concatenate(w, axis=1), np.empty((n, 3)))


def test_nonfinite_linearization_in_c_names_the_instruction():
    c = al.compile(lambda a, b: al.sqrt(a) / b, ["scalar", "scalar"]).with_c()
    before = al.counters["nonfinite_linearization"]
    with pytest.raises(al.NonFiniteError, match="sqrt|div"):
        c.linearize(np.array([1.0, -1.0, 4.0]), np.ones(3))
    assert al.counters["nonfinite_linearization"] == before + 1
