"""autolin: tracing, the four generated programs, simplification, instruction counts, bad input."""

from __future__ import annotations

import logging

import numpy as np
import pytest

import shared.autolin as al
from shared.autolin import ops as O
from shared.autolin import scalar as S


def unit_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_trace_records_ordinary_code_once():
    calls = []

    def f(q, v, s):
        calls.append(1)
        w = q * v + al.cross(v, [0.0, 0.0, 1.0]) * al.sin(s)
        return al.dot(w, w) / 2.0, q * q.conj()

    p = al.trace(f, ["quat", "vec3", "scalar"])
    assert len(calls) == 1
    assert [i.op for i in p.instrs] == ["rotate", "cross", "sin", "scale", "add.vec3", "dot", "div", "conj", "qmul"]
    assert all("test_autolin.py" in i.line for i in p.instrs)
    assert [p.types[o] for o in p.outputs] == ["scalar", "quat"]


def test_data_dependent_control_flow_names_the_line():
    def f(x):
        if x > 0:  # the offending line
            return x
        return -x

    before = al.counters["tracing_error"]
    with pytest.raises(al.TracingError, match=r"test_autolin\.py:\d+: data-dependent control flow"):
        al.trace(f, ["scalar"])
    assert al.counters["tracing_error"] == before + 1
    with pytest.raises(al.TracingError, match="control flow"):
        al.trace(lambda x: x if bool(x) else x, ["vec3"])

    def g(x):
        return x * float(x)  # a traced value turned into a number

    with pytest.raises(al.TracingError, match=r"test_autolin\.py:\d+: data-dependent control flow"):
        al.trace(g, ["scalar"])


def test_bad_trace_inputs_are_clear_errors():
    with pytest.raises(al.TracingError, match="constant of 2 numbers"):
        al.trace(lambda v: v + [1.0, 2.0], ["vec3"])
    with pytest.raises(al.TracingError, match="not a value traced"):
        al.trace(lambda v: 3.0, ["vec3"])
    with pytest.raises(al.TracingError, match="constant axis"):
        al.trace(lambda t, a: al.angle_axis(t, a), ["scalar", "vec3"])
    with pytest.raises(ValueError, match="unknown input types"):
        al.trace(lambda v: v, ["vec4"])


def test_rotation_chaining_counts_match_the_thesis():
    f = al.compile(lambda a, b: a * b, ["quat", "quat"])
    fw, rv = f.scalar["forward"].counts(), f.scalar["reverse"].counts()
    assert (fw["muls"], fw["adds"], fw["instructions"]) == (15, 18, 33)
    assert (rv["muls"], rv["adds"], rv["instructions"]) == (15, 15, 30)
    assert (fw["loads"], fw["stores"], fw["memory_ops"]) == (10, 3, 13)
    # the linearizer stores the first quaternion: a move, no arithmetic
    assert f.scalar["linearize"].counts()["instructions"] == 28
    assert set(f.scalar["forward"].nodes[i].op for i in f.scalar["forward"].live()) <= {"in", "add", "sub", "mul"}


def _qmul_scalar(a0, a1, a2, a3, b0, b1, b2, b3):
    return O.qmul((a0, a1, a2, a3), (b0, b1, b2, b3))


def _matmul_scalar(*x):
    return O.matmul(x[:9], x[9:])


def test_scalar_ad_baseline_counts_match_the_thesis():
    q = S.trace_scalar(_qmul_scalar, [f"x{i}" for i in range(8)])
    m = S.trace_scalar(_matmul_scalar, [f"x{i}" for i in range(18)])
    assert S.jvp_program(q).counts()["instructions"] == 60
    assert S.vjp_program(q).counts()["instructions"] == 56
    assert S.jvp_program(m).counts()["instructions"] == 99
    assert S.vjp_program(m).counts()["instructions"] == 90
    assert S.jvp_program(q).counts()["memory_ops"] == 20
    assert S.jvp_program(m).counts()["memory_ops"] == 45


def test_angle_axis_and_sin_gradients_need_no_trigonometry():
    f = al.compile(lambda t, q: al.angle_axis(t, [0, 0, 2.0]) * q, ["scalar", "quat"])
    for name in ("forward", "reverse"):
        c = f.scalar[name].counts()
        assert c["sin"] == c["cos"] == c["sqrt"] == c["div"] == 0
    g = al.compile(lambda x: al.sin(x) * 3.0, ["scalar"])
    fw = g.scalar["forward"].counts()
    assert fw["sin"] == fw["cos"] == 0 and fw["instructions"] == 2  # dx * cos(x) stored, times 3


def test_reverse_merges_multiple_reads_in_a_binary_tree():
    p = al.trace(lambda x: x * x + x * x * x, ["scalar"])
    rev = al.generate(p).block["reverse"]
    merges = [i for i in rev.instrs if i.op == "add.scalar.fwd"]
    assert len(merges) >= 3  # x is read five times
    f = al.generate(p)
    x = np.array([0.5, -2.0, 3.0])
    _, L = f.linearize(x)
    (g,) = f.reverse(L, np.ones(3))
    np.testing.assert_allclose(g, 2 * x + 3 * x * x, rtol=1e-14)


def test_simplification():
    b = S.Builder(simplify=False)
    x, y = b.input("x"), b.input("y")
    two = b.const(1.0) + b.const(1.0)            # constant folding
    z = (x * two) * b.const(1.0) + y * b.const(0.0)  # multiply by one, zero operator
    w = b.emit("mov", z) - b.const(0.0)          # redundant move, subtract zero
    dead = x * y * b.const(7.0)                  # unused
    b.const(2.0)                                 # equal constant
    b.prog.outputs = [w.i, b.const(2.0).i]
    del dead
    raw = b.prog.counts()
    p = S.simplify(b.prog)
    assert raw["instructions"] > p.counts()["instructions"] == 1
    assert [n.op for n in p.nodes].count("const") == 1  # the 2.0s deduplicated
    assert len(p.nodes) == 4  # x, y, 2.0, x * 2
    np.testing.assert_allclose(S.replay(p, [np.arange(3.0), np.ones(3)])[0], 2 * np.arange(3.0))


def test_accumulation_adds_rotation_vectors_to_quaternions():
    f = al.compile(lambda q, v: q * v, ["quat", "vec3"])
    rng = np.random.default_rng(3)
    q, v = unit_quats(rng, 4), rng.normal(size=(4, 3))
    d = rng.normal(size=(4, 3)) * 1e-4
    q2, v2 = f.accumulate([q, v], [d, d])
    np.testing.assert_allclose(np.linalg.norm(q2, axis=1), 1.0, rtol=1e-14)
    np.testing.assert_allclose(v2, v + d)
    # the step is the rotation exp(d) applied on the left, to first order
    dq = np.stack([np.ones(4), *(d / 2).T], axis=1)
    np.testing.assert_allclose(q2, np.stack(O.qmul(tuple(dq.T), tuple(q.T)), axis=1), atol=1e-7)


def test_nonfinite_linearization_names_the_instruction():
    def f(x):
        y = x * 2.0
        return al.sqrt(y - 1.0)  # negative for x < 0.5

    lin = al.compile(f, ["scalar"])
    before = al.counters["nonfinite_linearization"]
    with pytest.raises(al.NonFiniteError, match=r"instruction sqrt .*test_autolin\.py:\d+"):
        lin.linearize(np.array([1.0, 0.1]))
    assert al.counters["nonfinite_linearization"] == before + 1
    with pytest.raises(al.NonFiniteError, match="non-finite input"):
        lin.linearize(np.array([np.nan]))


def test_infinite_linearization_names_the_division():
    def f(x, y):
        s = x + y
        return s / (x - y)  # infinite where x == y

    lin = al.compile(f, ["scalar", "scalar"])
    lin.linearize(np.array([2.0]), np.array([1.0]))  # finite: no error
    before = al.counters["nonfinite_linearization"]
    with pytest.raises(al.NonFiniteError, match=r"instruction div .*test_autolin\.py:\d+"):
        lin.linearize(np.array([2.0, 1.0]), np.array([1.0, 1.0]))
    assert al.counters["nonfinite_linearization"] == before + 1


def test_operator_without_linearizer_uses_the_plain_rule_and_says_so(caplog):
    name = "test_cube_sum"
    if name not in al.OPS:
        al.register(al.Op(name, ("vec3",), "scalar", lambda v: (v[0] * v[0] * v[0] + v[1] * v[2],)))
    with pytest.raises(ValueError, match="needs a linearizer"):
        al.register(al.Op("test_bad", ("quat",), "scalar", lambda q: (q[0],)))
    O._warned.discard(name)
    before = al.counters["plain_rule"]
    with caplog.at_level(logging.WARNING, logger="shared.autolin.ops"):
        f = al.compile(lambda v: al.call(name, v) * 2.0, ["vec3"])
        al.compile(lambda v: al.call(name, v), ["vec3"])
    assert sum("no linearizer" in r.message for r in caplog.records) == 1  # said once
    assert al.counters["plain_rule"] >= before + 2  # counted each time it is used
    v = np.array([[1.0, 2.0, 3.0]])
    _, L = f.linearize(v)
    (dy,) = f.forward(L, np.array([[1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(dy, [6.0])
    (g,) = f.reverse(L, np.array([1.0]))
    np.testing.assert_allclose(g, [[6.0, 6.0, 4.0]])


def test_batched_execution_matches_single_samples():
    f = al.compile(lambda q, m, v: q * (m @ v), ["quat", "mat3", "vec3"])
    rng = np.random.default_rng(5)
    q, m, v = unit_quats(rng, 6), rng.normal(size=(6, 3, 3)), rng.normal(size=(6, 3))
    (y,), L = f.linearize(q, m, v)
    for k in range(6):
        (yk,), _ = f.linearize(q[k], m[k], v[k])
        np.testing.assert_allclose(yk, y[k], rtol=1e-13)
    r = np.stack([np.stack(O.qrot(tuple(q[k]), tuple(m[k] @ v[k]))) for k in range(6)])
    np.testing.assert_allclose(y, r, rtol=1e-12)
    with pytest.raises(ValueError, match="trailing size 4"):
        f.linearize(q[:, :3], m, v)


def test_static_memory_allocation_reuses_registers():
    from shared.autolin.memory import Executable, allocate

    f = al.compile(lambda a, b, c: (a * b) * (c * a.conj()), ["quat"] * 3)
    for name, p in f.scalar.items():
        reg, n = allocate(p)
        assert n < len(p.live()), name  # registers are shared once values are dead
        rng = np.random.default_rng(0)
        xs = [rng.normal(size=4) for _ in p.inputs]
        for got, want in zip(Executable(p)(xs), S.replay(p, xs), strict=True):
            np.testing.assert_array_equal(got, want)


def test_rotation_matrices_take_rotation_vector_gradients():
    f = al.compile(lambda a, b: a @ b, ["rot3", "rot3"])
    fw, rv = f.scalar["forward"].counts(), f.scalar["reverse"].counts()
    assert (fw["instructions"], rv["instructions"]) == (18, 15)  # V1 + R1 V2, (V3, R1^T V3)
    g = al.compile(lambda q, v: al.to_matrix(q) @ v, ["quat", "vec3"])
    h = al.compile(lambda q, v: q * v, ["quat", "vec3"])
    rng = np.random.default_rng(8)
    q, v, d, e = unit_quats(rng, 5), *(rng.normal(size=(5, 3)) for _ in range(3))
    (y1,), L1 = g.linearize(q, v)
    (y2,), L2 = h.linearize(q, v)
    np.testing.assert_allclose(y1, y2, atol=1e-14)
    np.testing.assert_allclose(g.forward(L1, d, e)[0], h.forward(L2, d, e)[0], atol=1e-14)
    r = np.stack([np.eye(3)] * 5)
    (r2,) = al.compile(lambda m: m, ["rot3"]).accumulate([r], [d])
    np.testing.assert_allclose(r2 @ np.swapaxes(r2, 1, 2), r, atol=1e-14)  # stays a rotation
