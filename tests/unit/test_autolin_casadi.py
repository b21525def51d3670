"""The CasADi references of bench/autolin.py compute the same J v and J^T w as autolin's
programs (rotation vectors converted to quaternion tangents), in CasADi's virtual machine and
through its generated C."""

from __future__ import annotations

import shutil

import casadi as ca
import numpy as np
import pytest

import shared.autolin as al
from shared.autolin import camera as C
from shared.autolin import casadi_reference as CR
from shared.autolin import ops as O
from shared.autolin.chain import AXES, CHAIN_TYPES, chain

MODES = ["vm"] + (["c"] if shutil.which("cc") or shutil.which("gcc") else [])


def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack(O.qmul(tuple(a.T), tuple(b.T)), axis=1)


def tangent(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """d/dt exp(t v) q at t = 0: the quaternion tangent of rotation vector v."""
    return 0.5 * qmul(np.concatenate([np.zeros((len(v), 1)), v], 1), q)


def samples(n: int, rng: np.random.Generator) -> list[np.ndarray]:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q2 = rng.normal(size=(n, 4))
    q2 /= np.linalg.norm(q2, axis=1, keepdims=True)
    intr = [np.c_[rng.uniform(400, 600, n), rng.uniform(400, 600, n), rng.uniform(300, 340, n)],
            np.c_[rng.uniform(220, 260, n), rng.normal(0, 0.05, (n, 2))], rng.normal(0, 0.01, (n, 3))]
    t = rng.normal(0, 0.1, (n, 3)) + [0, 0, 1.0]
    return [q, rng.normal(0, 0.1, (n, 3)), *intr, q2, t, rng.uniform(-0.2, 0.2, (n, 3)), rng.normal(size=n),
            rng.normal(size=n)]


BACKENDS = ["numpy"] + (["c"] if shutil.which("cc") else [])


@pytest.fixture(scope="module")
def camera_programs() -> dict[str, al.Linearized]:
    f = al.compile(C.reprojection, C.PARAM_TYPES + C.DATA_TYPES)
    return {"numpy": f, **({"c": f.with_c()} if "c" in BACKENDS else {})}


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mode", MODES)
def test_casadi_products_match_autolin(mode: str, backend: str, camera_programs: dict):
    rng = np.random.default_rng(4)
    n = 17  # odd: the C programs' last, partial group of samples is exercised
    xs = samples(n, rng)
    f = camera_programs[backend]
    _, L = f.linearize(*xs)
    jv, jtv = CR.products(*CR.camera_expr(), "camera")
    fj, fr = CR.batched(jv, n, mode), CR.batched(jtv, n, mode)
    X = CR.columns(xs)
    d = [rng.normal(size=x.shape[:1] + (3,) if t == "quat" else x.shape) for x, t in zip(xs, f.in_types, strict=True)]
    dq = [tangent(x, v) if t == "quat" else v for x, v, t in zip(xs, d, f.in_types, strict=True)]
    np.testing.assert_allclose(np.array(fj(X, CR.columns(dq))).T, np.stack(f.forward(L, *d), 1), rtol=1e-12,
                               atol=1e-12)
    w = [rng.normal(size=n), rng.normal(size=n)]
    g = np.array(fr(X, CR.columns(w))).T  # (n, 28): quaternion-space gradients
    mine = f.reverse(L, *w)
    k = 0
    for x, t, gm in zip(xs, f.in_types, mine, strict=True):
        size = 4 if t == "quat" else (x.shape[1] if x.ndim > 1 else 1)
        gc = g[:, k:k + size]
        if t == "quat":  # rotation-vector gradient: component i is <g_q, tangent(q, e_i)>
            gc = np.stack([np.sum(gc * tangent(x, np.tile(e, (n, 1))), 1) for e in np.eye(3)], 1)
        np.testing.assert_allclose(gc.reshape(gm.shape), gm, rtol=1e-12, atol=1e-12)
        k += size


def test_chain_casadi_matches_autolin_values():
    x, y = CR.chain_expr(AXES)
    rng = np.random.default_rng(5)
    vals = rng.normal(size=x.numel())
    for k in range(5):
        vals[4 * k:4 * k + 4] /= np.linalg.norm(vals[4 * k:4 * k + 4])
    out = np.array(ca.Function("chain", [x], [y])(vals)).ravel()

    f = al.compile(chain, CHAIN_TYPES)
    parts = np.split(vals, np.cumsum(CR.CHAIN_SIZES)[:-1])
    (q, t), _ = f.linearize(*[p[None] if len(p) > 1 else p for p in parts])
    np.testing.assert_allclose(out, np.r_[q[0], t[0]], atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_chain_products_match_casadi(backend: str):
    """The five-frame chain's J v (position rows) and J^T w (a position cotangent) against CasADi's
    jtimes on random inputs, to 1e-12."""

    f = al.compile(chain, CHAIN_TYPES)
    f = f.with_c() if backend == "c" else f
    rng = np.random.default_rng(6)
    n = 9
    xs = [rng.normal(size=(n, O.SIZE[t])) if t != "scalar" else rng.normal(size=n) for t in CHAIN_TYPES]
    xs = [x / np.linalg.norm(x, axis=1, keepdims=True) if t == "quat" else x
          for x, t in zip(xs, CHAIN_TYPES, strict=True)]
    d = [rng.normal(size=(n, 3)) if t != "scalar" else rng.normal(size=n) for t in CHAIN_TYPES]
    dq = [tangent(x, v) if t == "quat" else v for x, v, t in zip(xs, d, CHAIN_TYPES, strict=True)]
    jv, jtv = CR.products(*CR.chain_expr(AXES), "chain")
    X = CR.columns(xs)
    _, L = f.linearize(*xs)
    np.testing.assert_allclose(np.array(jv.map(n)(X, CR.columns(dq))).T[:, 4:], f.forward(L, *d)[1], rtol=1e-12,
                               atol=1e-12)
    w = rng.normal(size=(n, 3))
    g = np.array(jtv.map(n)(X, CR.columns([np.zeros((n, 4)), w]))).T
    k = 0
    for x, t, gm in zip(xs, CHAIN_TYPES, f.reverse(L, np.zeros((n, 3)), w), strict=True):
        size = 4 if t == "quat" else (3 if t == "vec3" else 1)
        gc = g[:, k:k + size]
        if t == "quat":
            gc = np.stack([np.sum(gc * tangent(x, np.tile(e, (n, 1))), 1) for e in np.eye(3)], 1)
        np.testing.assert_allclose(gc.reshape(gm.shape), gm, rtol=1e-12, atol=1e-12)
        k += size
