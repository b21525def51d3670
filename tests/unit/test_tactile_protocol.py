"""Tactile protocol v2 against its committed vectors, plus its own decoder properties (those every
stream decoder shares are in test_protocols.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.protocols import tactile
from tests.unit.test_protocols import accounted

CASES = json.loads(tactile.VECTORS_PATH.read_text())
FRAME_CASES = [c for c in CASES if "real" in c]
FRAMES = [bytes.fromhex(c["bytes"]) for c in FRAME_CASES]


def case_frame(case: dict) -> tactile.TactileFrame:
    z = (np.array(case["real"]) + 1j * np.array(case["imag"])).reshape(16, 16).astype(np.complex64)
    imu = None if case["imu"] is None else np.array(case["imu"], np.float32)
    return tactile.TactileFrame(case["sequence"], case["timestamp_us"], z, imu, case["tx_mask"], case["rx_mask"],
                                case["status"])


def test_vectors_are_current():
    assert tactile.make_vectors() == CASES


@pytest.mark.parametrize("case", FRAME_CASES, ids=lambda c: f"tx{c['tx_mask']:04x}-rx{c['rx_mask']:04x}")
def test_frame_vectors_encode_and_decode_exactly(case):
    data = bytes.fromhex(case["bytes"])
    f = case_frame(case)
    assert tactile.encode_frame(f) == data
    assert len(data) == tactile.frame_bytes(f.tx_mask, f.rx_mask, 0 if f.imu is None else len(f.imu))
    dec = tactile.StreamDecoder()
    (got,) = dec.feed(data)
    # Raw correlator integers in, what survives the blocks out (exact where |v| <= 32767).
    np.testing.assert_array_equal(got.impedance, tactile.quantize(f.impedance, f.tx_mask, f.rx_mask))
    small = np.abs(f.impedance.real).max() <= 32767 and np.abs(f.impedance.imag).max() <= 32767
    assert not small or np.array_equal(got.impedance, f.impedance)
    assert (got.sequence, got.timestamp_us, got.tx_mask, got.rx_mask, got.status) == \
        (f.sequence, f.timestamp_us, f.tx_mask, f.rx_mask, f.status)
    if f.imu is not None:
        np.testing.assert_allclose(got.imu, f.imu, atol=tactile.ACCEL_LSB)


def test_register_vectors_and_reply():
    by_kind = {next(k for k in c if k != "bytes"): c for c in CASES if "real" not in c}
    w, r, rep = by_kind["register_write"], by_kind["register_read"], by_kind["register_reply"]
    assert tactile.encode_command(*w["register_write"]).hex() == w["bytes"]
    assert tactile.encode_command(*r["register_read"]).hex() == r["bytes"]
    reply = tactile.decode_reply(bytes.fromhex(rep["bytes"]))
    assert [reply.address, reply.value, reply.status] == rep["register_reply"]
    with pytest.raises(tactile.FrameError):
        tactile.decode_reply(bytes.fromhex(rep["bytes"])[:-1])
    with pytest.raises(tactile.FrameError):
        tactile.encode_command(0x10000, 1)


def test_glove_frame_is_small_enough_for_two_gloves_at_1khz_on_12_mbaud():
    assert tactile.frame_bytes(0xFFFF, 0x003F) == 423
    assert 2 * 1000 * 10 * tactile.frame_bytes(0xFFFF, 0x003F, 1) < 12e6


def test_exponent_is_minimal_and_rounding_is_half_up():
    v = np.array([32767.0, 32767.5, 65534.0, 65535.0, -1.5, 0.0, 2.5, 3.5] + [0.0] * 8)
    # Blocks of one value each to look at the exponent rule.
    assert tactile.block_exponents(v[:1]).tolist() == [0]
    assert tactile.block_exponents(v[1:2]).tolist() == [1]
    assert tactile.block_exponents(v[2:3]).tolist() == [1]
    assert tactile.block_exponents(v[3:4]).tolist() == [2]
    assert tactile.block_exponents(np.zeros(16)).tolist() == [tactile.EXP_MIN]
    # Peak 65535 -> e = 2: 5/4 = 1.25 -> 1, 6/4 = 1.5 -> 2 (half up), -6/4 = -1.5 -> -1 (half up).
    data = tactile.encode_blocks(np.array([65535.0, 5.0, 6.0, -6.0]))
    assert data[0] == 2 and np.frombuffer(data[1:], "<i2").tolist() == [16384, 1, 2, -1]


def test_quantize_error_is_bounded_and_outside_masks_is_zero():
    rng = np.random.default_rng(1)
    z = (rng.normal(0, 1, (16, 16)) + 1j * rng.lognormal(0, 3, (16, 16))).astype(np.complex64)
    q = tactile.quantize(z)
    vals = np.stack([z.real, z.imag], axis=2).reshape(-1, 16)
    qv = np.stack([q.real, q.imag], axis=2).reshape(-1, 16)
    peak = np.abs(vals).max(axis=1, keepdims=True)
    assert np.all(np.abs(qv - vals) <= peak / 32767)
    np.testing.assert_array_equal(tactile.quantize(q), q)  # idempotent
    qm = tactile.quantize(z, 0x00FF, 0x0003)
    assert np.all(qm[8:, :] == 0) and np.all(qm[:, 2:] == 0) and np.abs(qm[:8, :2]).sum() > 0


def test_encoder_rejects_bad_input():
    with pytest.raises(tactile.FrameError):
        tactile.encode_frame(tactile.TactileFrame(0, 0, np.zeros((16, 15), np.complex64)))
    with pytest.raises(tactile.FrameError):
        tactile.encode_frame(tactile.TactileFrame(0, 0, np.full((16, 16), np.nan, np.complex64)))
    with pytest.raises(tactile.FrameError):
        tactile.encode_frame(tactile.TactileFrame(0, 0, np.zeros((16, 16), np.complex64), np.zeros((9, 6))))


def test_malformed_but_crc_valid_payload_is_counted_not_raised():
    from shared.protocols.framing import frame

    good = FRAMES[0]
    bad = frame(tactile.TYPE_FRAME, good[5:-4][:-1])  # one matrix byte short, valid CRC
    dec = tactile.StreamDecoder()
    assert len(dec.feed(bad + good)) == 1
    assert dec.stats["malformed"] == 1 and dec.stats["malformed_bytes"] == len(bad)


def test_sequence_gaps_count_lost_frames():
    dec = tactile.StreamDecoder()
    z = np.zeros((16, 16), np.complex64)
    for s in (5, 6, 9, 10):
        dec.feed(tactile.encode_frame(tactile.TactileFrame(s, 0, z)))
    assert dec.stats["sequence_gaps"] == 1 and dec.stats["frames_lost"] == 2


def test_register_file_model():
    regs = tactile.RegisterFile()
    assert regs.handle(tactile.RegisterCommand(tactile.REG_ID, None)).value == tactile.DEVICE_ID
    assert regs.handle(tactile.RegisterCommand(tactile.REG_ID, 5)).status == tactile.REPLY_READ_ONLY
    assert regs.handle(tactile.RegisterCommand(0x0002, None)).status == tactile.REPLY_BAD_ADDRESS
    assert regs.handle(tactile.RegisterCommand(tactile.REG_RX_ENABLE, 0x1003F)).value == 0x003F
    cmds = tactile.CommandDecoder().feed(b"junk" + tactile.encode_command(0x104, 77) + tactile.encode_command(0))
    assert [(c.address, c.value) for c in cmds] == [(0x104, 77), (0, None)]


@settings(max_examples=150, deadline=None)
@given(st.sampled_from(FRAMES), st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)), min_size=1,
                                        max_size=8))
def test_mutated_frames_are_rejected_and_the_next_good_frame_recovered(frame, flips):
    data = bytearray(frame)
    for pos, val in flips:
        data[pos % len(data)] = val
    # A forged length can make the decoder wait for up to a maximum frame before it rejects.
    hidden = -(-(tactile.MAX_PAYLOAD + 9) // len(frame))
    n = hidden + 2
    decoder = tactile.StreamDecoder()
    out = decoder.feed(bytes(data) + frame * n)
    if bytes(data) != frame:
        assert n - hidden <= len(out) <= n  # the mutated frame never decodes
        assert decoder.stats["bytes_discarded"] > 0 or decoder.stats["malformed"] > 0
    assert all(isinstance(o, tactile.TactileFrame) for o in out)
    assert accounted(decoder) == n * len(frame) + len(data)
