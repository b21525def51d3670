"""Robot control-board protocol: committed vectors, round trips, stream recovery, fuzzed round trips
(the properties every stream decoder shares are in test_protocols.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.protocols import robot_board as rb
from shared.protocols.framing import frame

VECTOR_FILE = Path(__file__).resolve().parents[2] / "shared/protocols/vectors/robot_board.json"
VECTORS = json.loads(VECTOR_FILE.read_text())
FRAMES = [bytes.fromhex(c["bytes"]) for c in VECTORS]


def test_vectors_decode_field_by_field_and_re_encode_byte_exact():
    kinds = set()
    for case in VECTORS:
        data = bytes.fromhex(case["bytes"])
        msg = rb.decode(data)
        kind, fields = next((k, v) for k, v in case.items() if k != "bytes")
        kinds.add(kind)
        fields = dict(fields)
        parts = [(msg, fields)] + ([(msg.command, fields.pop("command"))] if kind == "plan" else [])
        for obj, want_fields in parts:
            for name, want in want_fields.items():
                got = getattr(obj, name)
                if isinstance(got, np.ndarray):
                    assert got.tolist() == want, f"{kind}.{name}"
                else:
                    assert got == want, f"{kind}.{name}"
        assert rb.encode(msg) == data
    assert kinds == {"command", "plan", "feedback", "config"}
    assert rb.vector_cases() == VECTORS  # the committed file is what the code produces


def test_sizes_match_the_spec():
    n = len(rb.JOINTS)
    assert len(rb.encode_command(rb.CommandFrame.brake(0, n))) == 9 + 5 + 21 * n
    fb = rb.FeedbackFrame(0, 0, 0, np.zeros(n), np.zeros(n), np.zeros(n))
    assert len(rb.encode_feedback(fb)) == 9 + 31 + 13 * n
    assert len(rb.encode_config(rb.ConfigFrame())) == 9 + 9
    plan = rb.PlanFrame(rb.CommandFrame.brake(0, n), np.zeros((6, n)), np.zeros((6, n)), 8000)
    assert len(rb.encode_plan(plan)) == 9 + 8 + 21 * n + 6 * 8 * n


def test_a_plan_interpolates_between_its_knots_and_holds_the_last():
    cmd = rb.CommandFrame.hold(4, np.array([0.0, 1.0]))
    cmd.velocity[:] = [1.0, 0.0]
    plan = rb.decode(rb.encode(rb.PlanFrame(cmd, np.array([[0.008, 1.0], [0.016, 0.5]]),
                                            np.array([[1.0, 0.0], [1.0, -50.0]]), 8000)))
    assert isinstance(plan, rb.PlanFrame) and plan.knots == 3 and plan.span_s == pytest.approx(0.016)
    assert plan.at(-0.001) is plan.command and plan.at(0.0).position.tolist() == [0.0, 1.0]
    mid = plan.at(0.012)
    assert mid.position == pytest.approx([0.012, 0.75]) and mid.velocity == pytest.approx([1.0, -25.0])
    assert plan.at(0.5).position == pytest.approx([0.016, 0.5]) and plan.at(0.5).velocity[1] == pytest.approx(-50.0)
    assert mid.sequence == 4 and (mid.mode == cmd.mode).all()


def test_a_plan_with_inconsistent_knots_is_refused_or_counted():
    n = 3
    with pytest.raises(rb.FrameError, match="knots have shapes"):
        rb.encode_plan(rb.PlanFrame(rb.CommandFrame.brake(0, n), np.zeros((2, n)), np.zeros((1, n)), 8000))
    with pytest.raises(rb.FrameError, match="knots, 1 to"):
        rb.encode_plan(rb.PlanFrame(rb.CommandFrame.brake(0, n), np.zeros((rb.MAX_KNOTS, n)),
                                    np.zeros((rb.MAX_KNOTS, n)), 8000))
    d = rb.StreamDecoder()
    short = frame(rb.TYPE_PLAN, rb.PLAN_HEAD.pack(1, n, 3, 8000) + bytes(21 * n + 8 * n))  # one knot short
    zero_spacing = frame(rb.TYPE_PLAN, rb.PLAN_HEAD.pack(2, n, 1, 0) + bytes(21 * n))
    assert d.feed(short + zero_spacing) == [] and d.stats["malformed"] == 2


def test_plans_and_commands_share_one_sequence():
    d = rb.StreamDecoder()
    n = 2
    plan = rb.PlanFrame(rb.CommandFrame.brake(8, n), np.zeros((1, n)), np.zeros((1, n)), 4000)
    d.feed(rb.encode(rb.CommandFrame.brake(7, n)) + rb.encode(plan) + rb.encode(rb.CommandFrame.brake(9, n)))
    assert d.stats["frames"] == 3 and d.stats["sequence_gaps"] == 0


def test_joint_commands_round_trip_through_a_frame():
    joints = [rb.JointCommand(rb.Mode.IMPEDANCE, 0.125, -0.5, 1.5, 300.0, 12.0),
              rb.JointCommand(rb.Mode.EFFORT, 0, 0, -2.0)]
    msg = rb.decode(rb.encode(rb.CommandFrame.from_joints(9, joints)))
    assert [msg.joint(i) for i in range(msg.n)] == joints
    assert msg.joint(0).mode is rb.Mode.IMPEDANCE


def test_pneumatic_mode_round_trips_and_is_in_the_vectors():
    joints = [rb.JointCommand(rb.Mode.PNEUMATIC, 0.75), rb.JointCommand(rb.Mode.POSITION, -0.25)]
    msg = rb.decode(rb.encode(rb.CommandFrame.from_joints(3, joints)))
    assert msg.joint(0).mode is rb.Mode.PNEUMATIC and msg.joint(0).position == 0.75
    assert [msg.joint(i) for i in range(msg.n)] == joints
    # The mixed vector's sixth joint: after the frame header, sequence and n, and five 21-byte rows.
    assert rb.Mode.PNEUMATIC == 5 and bytes.fromhex(VECTORS[1]["bytes"])[5 + 5 + 5 * 21] == 5
    assert VECTORS[1]["command"]["mode"][5] == 5


def test_non_finite_setpoints_travel_unchanged_so_the_board_can_reject_them():
    c = rb.CommandFrame.hold(1, np.array([np.nan, np.inf, -np.inf]))
    out = rb.decode(rb.encode(c))
    assert np.isnan(out.position[0]) and out.position[1] == np.inf and out.position[2] == -np.inf


def test_encoder_refuses_inconsistent_messages():
    with pytest.raises(rb.FrameError, match="shape"):
        rb.encode_command(rb.CommandFrame(0, np.zeros(3, np.uint8), np.zeros(2), np.zeros(3), np.zeros(3),
                                          np.zeros(3), np.zeros(3)))
    with pytest.raises(rb.FrameError, match="together"):
        rb.encode_config(rb.ConfigFrame(10_000, lower=np.zeros(2)))
    with pytest.raises(rb.FrameError, match="at most"):
        rb.encode_command(rb.CommandFrame.brake(0, rb.MAX_JOINTS + 1))


def test_good_crc_with_a_wrong_length_is_counted_as_malformed():
    bad = frame(rb.TYPE_COMMAND, rb.CMD_HEAD.pack(1, 3) + bytes(21 * 2))  # says 3 joints, carries 2
    d = rb.StreamDecoder()
    assert d.feed(bad + FRAMES[0]) and d.stats["malformed"] == 1
    assert "expected for 3 joints" in d.last_error
    with pytest.raises(rb.FrameError, match="expected for 3 joints"):
        rb.decode(bad)


def test_stream_recovers_after_garbage_and_counts_it():
    good = rb.encode_command(rb.CommandFrame.hold(5, np.zeros(10)))
    corrupted = bytearray(good)
    corrupted[20] ^= 0x40
    garbage = b"\x00\xa5\x5a\xff" + bytes(corrupted) + b"\xa5"
    d = rb.StreamDecoder()
    out = []
    stream = garbage + good
    for i in range(0, len(stream), 7):  # arbitrary read boundaries
        out += d.feed(stream[i:i + 7])
    assert len(out) == 1 and out[0].sequence == 5
    assert d.stats["crc_errors"] >= 1 and d.stats["resyncs"] >= 1
    assert d.stats["bytes_discarded"] == len(garbage)


def test_sequence_gaps_and_lost_frames_are_counted_per_type():
    d = rb.StreamDecoder()
    n = 10
    z = np.zeros(n)
    fb = [rb.encode_feedback(rb.FeedbackFrame(s, s, 0, z, z, z)) for s in (1, 2, 5)]
    cmds = [rb.encode_command(rb.CommandFrame.brake(s, n)) for s in (100, 101)]
    d.feed(fb[0] + cmds[0] + fb[1] + cmds[1] + fb[2])  # interleaved types do not count as gaps
    assert d.stats["sequence_gaps"] == 1 and d.stats["frames_lost"] == 2
    d.feed(rb.encode_command(rb.CommandFrame.brake(0, n)))  # a host restart: one gap, no 4e9 losses
    assert d.stats["sequence_gaps"] == 2 and d.stats["frames_lost"] == 2


def test_sequence_wraps_without_a_gap():
    d = rb.StreamDecoder()
    d.feed(rb.encode(rb.CommandFrame.brake(0xFFFFFFFF, 2)) + rb.encode(rb.CommandFrame.brake(0, 2)))
    assert d.stats["sequence_gaps"] == 0 and d.stats["frames"] == 2


finite32 = st.floats(width=32, allow_nan=False, allow_infinity=False)


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2 ** 32 - 1),
       st.lists(st.tuples(st.sampled_from(list(rb.Mode)), finite32, finite32, finite32, finite32, finite32),
                min_size=0, max_size=rb.MAX_JOINTS))
def test_fuzz_any_command_round_trips(seq, rows):
    c = rb.CommandFrame.from_joints(seq, [rb.JointCommand(*r) for r in rows])
    out = rb.decode(rb.encode(c))
    assert out.sequence == seq and [out.joint(i) for i in range(out.n)] == [c.joint(i) for i in range(c.n)]
