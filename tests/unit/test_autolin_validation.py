"""autolin's three validation suites (thesis 3.3): finite differences over split input
domains, a self-test against the framework's own scalar AD, and chains of five random
coordinate frames against torch.func in double precision (MSE <= 1e-15)."""

from __future__ import annotations

import numpy as np
import pytest

import shared.autolin as al
from shared.autolin import ops as O
from shared.autolin import scalar as S
from shared.autolin.chain import chain

N = 64  # samples per domain, batched


def qexp(v: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.concatenate([np.cos(th / 2), np.sinc(th / (2 * np.pi)) / 2 * v], axis=-1)


def qm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack(O.qmul(tuple(np.moveaxis(a, -1, 0)), tuple(np.moveaxis(b, -1, 0))), axis=-1)


def qconj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1, -1, -1])


def qmat(q: np.ndarray) -> np.ndarray:
    return np.stack(O.quat_to_matrix(tuple(np.moveaxis(q, -1, 0))), axis=-1).reshape(q.shape[:-1] + (3, 3))


def vee(a: np.ndarray) -> np.ndarray:
    """The vector of the skew-symmetric part of a 3x3 matrix."""
    s = 0.5 * (a - np.swapaxes(a, -1, -2))
    return np.stack([s[..., 2, 1], s[..., 0, 2], s[..., 1, 0]], axis=-1)


def perturb(typ: str, x: np.ndarray, d: np.ndarray, eps: float) -> np.ndarray:
    if typ == "quat":
        return qm(qexp(eps * d), x)
    return qmat(qexp(eps * d)) @ x if typ == "rot3" else x + eps * d


def difference(typ: str, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a - b in the gradient type: the rotation vector taking b to a for quaternions."""
    if typ == "quat":
        r = qm(a, qconj(b))
        return 2 * r[..., 1:] * np.sign(r[..., :1])
    return vee(a @ np.swapaxes(b, -1, -2)) if typ == "rot3" else a - b


def sample(typ: str, rng: np.random.Generator, lo: float = -2.0, hi: float = 2.0) -> np.ndarray:
    if typ in ("quat", "rot3"):
        q = rng.normal(size=(N, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        return q if typ == "quat" else qmat(q)
    shape = {"scalar": (N,), "vec3": (N, 3), "mat3": (N, 3, 3)}[typ]
    return rng.uniform(lo, hi, size=shape)


def grad_sample(typ: str, rng: np.random.Generator) -> np.ndarray:
    return rng.normal(size={"scalar": (N,), "vec3": (N, 3), "mat3": (N, 3, 3)}[O.GRAD[typ]])


def inner(a: list[np.ndarray], b: list[np.ndarray]) -> np.ndarray:
    return sum(np.sum((x * y).reshape(N, -1), axis=1) for x, y in zip(a, b, strict=True))


# operator, argument domains (split ranges for operators with undefined regions)
CASES = [
    ("add.vec3", [None, None]), ("sub.mat3", [None, None]), ("neg.scalar", [None]),
    ("mul", [None, None]), ("div", [None, (0.2, 5.0)]), ("div", [None, (-5.0, -0.2)]),
    ("sin", [(-10.0, 10.0)]), ("cos", [(-10.0, 10.0)]),
    ("sqrt", [(1e-2, 1.0)]), ("sqrt", [(1.0, 1e3)]),
    ("scale", [None, None]), ("dot", [None, None]), ("cross", [None, None]),
    ("matmul", [None, None]), ("matvec", [None, None]),
    ("qmul", [None, None]), ("rotate", [None, None]), ("conj", [None]),
    ("rmul", [None, None]), ("rrotate", [None, None]), ("to_matrix", [None]),
    ("angle_axis", [(-4.0, 4.0)]),
]


def op_program(name: str) -> tuple[al.Linearized, tuple[str, ...]]:
    if name == "angle_axis":
        return al.compile(lambda t: al.angle_axis(t, [1.0, -2.0, 0.5]), ["scalar"]), ("scalar",)
    types = O.OPS[name].arg_types
    return al.compile(lambda *a: al.call(name, *a), list(types)), types


def domain_inputs(types: tuple[str, ...], domains: list, rng: np.random.Generator) -> list[np.ndarray]:
    return [sample(t, rng, *(dom or (-2.0, 2.0))) for t, dom in zip(types, domains, strict=True)]


@pytest.mark.parametrize(("name", "domains"), CASES, ids=[f"{c[0]}{c[1]}" for c in CASES])
def test_suite1_finite_differences(name: str, domains: list):
    rng = np.random.default_rng(abs(hash((name, str(domains)))) % 2**32)
    f, types = op_program(name)
    out_t = f.out_types[0]
    xs = domain_inputs(types, domains, rng)
    ds = [grad_sample(t, rng) for t in types]
    (y,), L = f.linearize(*xs)
    (dy,) = f.forward(L, *ds)
    eps = 1e-6
    (yp,), _ = f.linearize(*[perturb(t, x, d, eps) for t, x, d in zip(types, xs, ds, strict=True)])
    (ym,), _ = f.linearize(*[perturb(t, x, d, -eps) for t, x, d in zip(types, xs, ds, strict=True)])
    fd = difference(out_t, yp, ym) / (2 * eps)
    np.testing.assert_allclose(dy, fd, rtol=1e-6, atol=1e-6 * (1 + np.abs(fd).max()))
    # the reverse program is the adjoint of the forward one: <J d, w> = <d, J^T w>
    w = grad_sample(O.GRAD[out_t], rng)
    gs = f.reverse(L, w)
    np.testing.assert_allclose(inner([dy], [w]), inner(ds, gs), rtol=1e-12, atol=1e-12)


def test_suite1_undefined_domain_is_reported():
    f, _ = op_program("sqrt")
    with pytest.raises(al.NonFiniteError, match="sqrt"):
        f.linearize(np.linspace(-1.0, -0.1, N))


def rv_to_dq(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The quaternion tangent of the perturbation exp(v) q."""
    return 0.5 * qm(np.concatenate([np.zeros(v.shape[:-1] + (1,)), v], axis=-1), q)


def dq_to_rv(q: np.ndarray, dq: np.ndarray) -> np.ndarray:
    return 2 * qm(dq, qconj(q))[..., 1:]


def tangent_in(t: str, x: np.ndarray, d: np.ndarray) -> np.ndarray:
    """A rotation-vector gradient as the value type's tangent (what scalar AD propagates)."""
    if t == "quat":
        return rv_to_dq(x, d)
    if t == "rot3":
        z = np.zeros(N)
        skew = np.stack([z, -d[:, 2], d[:, 1], d[:, 2], z, -d[:, 0], -d[:, 1], d[:, 0], z], 1).reshape(N, 3, 3)
        return skew @ x
    return d


def tangent_out(t: str, y: np.ndarray, dy: np.ndarray) -> np.ndarray:
    if t == "quat":
        return dq_to_rv(y, dy)
    if t == "rot3":
        return vee(dy.reshape(N, 3, 3) @ np.swapaxes(y, -1, -2))
    return dy


@pytest.mark.parametrize("name", list(dict.fromkeys(n for n, _ in CASES)))
def test_suite2_self_test_against_scalar_ad(name: str):
    """Block forward rules against the framework's own scalar AD of each operator's eval."""
    rng = np.random.default_rng(7)
    f, types = op_program(name)
    op = O.OPS[f.source.instrs[0].op]
    domains = dict(CASES).get(name, [None] * len(types))
    domains = [(0.2, 5.0) if (name, k) in (("div", 1), ("sqrt", 0)) else d for k, d in enumerate(domains)]
    xs = domain_inputs(types, domains, rng)
    ds = [grad_sample(t, rng) for t in types]
    sizes = [O.SIZE[t] for t in types]
    names = [f"x{k}" for k in range(sum(sizes))]

    def flat_eval(*s):
        parts, i = [], 0
        for n in sizes:
            parts.append(tuple(s[i:i + n]))
            i += n
        return list(op.eval(*parts))

    jp = S.jvp_program(S.trace_scalar(flat_eval, names))
    flat_x = [c for x, t in zip(xs, types, strict=True) for c in np.moveaxis(x.reshape(N, -1), -1, 0)]
    dq = [tangent_in(t, x, d) for x, d, t in zip(xs, ds, types, strict=True)]
    flat_d = [c for d in dq for c in np.moveaxis(d.reshape(N, -1), -1, 0)]
    ref = np.stack([np.broadcast_to(r, (N,)) for r in S.replay(jp, flat_x + flat_d)], axis=-1)
    (y,), L = f.linearize(*xs)
    (dy,) = f.forward(L, *ds)
    ref = tangent_out(f.out_types[0], y, ref)
    np.testing.assert_allclose(dy.reshape(N, -1), ref.reshape(N, -1), rtol=1e-12, atol=1e-12)


# --- suite 3: chains of five random coordinate frames against torch.func -----------------
def test_suite3_five_frame_chains_match_torch_func(record_property):
    torch = pytest.importorskip("torch")
    from torch.func import jvp, vjp

    types = ["quat"] * 5 + ["vec3"] * 5 + ["scalar"] * 5 + ["vec3"]
    f = al.compile(chain, types)
    rng = np.random.default_rng(11)
    xs = [sample(t, rng) for t in types]
    ds = [grad_sample(O.GRAD[t], rng) for t in types]
    (qo, po), L = f.linearize(*xs)
    dqo, dpo = f.forward(L, *ds)
    wq, wp = rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    gs = f.reverse(L, wq, wp)

    from shared.autolin.torch_reference import five_frame_chain

    ref = five_frame_chain([[0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0], [0, 0.6, 0.8], [0.48, 0.6, 0.64]])

    tx = tuple(torch.tensor(x) for x in xs)
    tangents = tuple(torch.tensor(rv_to_dq(x, d) if t == "quat" else d) for x, d, t in zip(xs, ds, types, strict=True))
    (rq, rp), (rdq, rdp) = jvp(ref, tx, tangents)
    err = [np.asarray(qo) - rq.numpy(), po - rp.numpy(), rv_to_dq(qo, dqo) - rdq.numpy(), dpo - rdp.numpy()]

    _, pull = vjp(ref, *tx)
    # the rotation-vector cotangent wq as a quaternion cotangent: w4 . dq = wq . dq_to_rv(q, dq)
    w4 = np.stack([np.sum(wq * dq_to_rv(qo, np.broadcast_to(e, (N, 4))), axis=1) for e in np.eye(4)], axis=1)
    rg = pull((torch.tensor(w4), torch.tensor(wp)))
    for x, g, r, t in zip(xs, gs, rg, types, strict=True):
        r = r.numpy()
        if t == "quat":  # its rotation-vector gradient: r . rv_to_dq(q, e_i)
            r = np.stack([np.sum(r * rv_to_dq(x, np.broadcast_to(e, (N, 3))), axis=1) for e in np.eye(3)], axis=1)
        err.append(g - r)
    mse = np.mean(np.concatenate([e.reshape(-1) for e in err]) ** 2)
    record_property("mse", float(mse))
    assert mse <= 1e-15
    assert max(np.abs(e).max() for e in err) < 1e-9
