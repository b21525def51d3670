"""The tactile readout protocol (glove readout module <-> host). Spec: docs/protocols/tactile.md.

One frame per readout window: sequence, device time, optional IMU samples and the 16x16 complex
impedance matrix in shared-exponent blocks (thesis 5.4): each block of 16 real or imaginary
values stores one signed exponent byte and 16 signed 16-bit little-endian mantissas,
value = mantissa * 2**exp (a 1056-byte matrix instead of 2048 bytes of float32).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from shared.protocols.framing import FrameDecoder, frame

ROWS = COLS = 16
BLOCK = 16
N_VALUES = 2 * ROWS * COLS  # real and imaginary parts
N_BLOCKS = N_VALUES // BLOCK
MANTISSA_MAX = 32767
BLOCK_BYTES = 1 + 2 * BLOCK

TYPE_FRAME = 0x01
TYPE_REPLY = 0x02
TYPE_WRITE = 0x10
TYPE_READ = 0x11

FRAME_HEAD = struct.Struct("<IQB")  # sequence, timestamp_us, imu sample count
IMU_SAMPLE = struct.Struct("<6h")  # ax ay az (1 mg/LSB... see ACCEL_LSB) gx gy gz
ACCEL_LSB = 9.80665 / 2048.0  # m/s^2 per LSB (±16 g range)
GYRO_LSB = np.radians(2000.0) / 32768.0  # rad/s per LSB (±2000 dps)
MAX_IMU = 8
MAX_PAYLOAD = FRAME_HEAD.size + MAX_IMU * IMU_SAMPLE.size + N_BLOCKS * BLOCK_BYTES
FRAME_BYTES = MAX_PAYLOAD - MAX_IMU * IMU_SAMPLE.size + 9  # without IMU, framing included
REG = struct.Struct("<HI")  # address, value
REPLY = struct.Struct("<HIB")  # address, value, status (0 ok, 1 bad address, 2 read-only)

# Configuration registers of the readout core (hdl/tactile).
REGISTERS = {
    0x0000: "id",  # read-only: 0x58540001 ("XT", version 1)
    0x0004: "window_cycles",  # correlation window in ADC samples
    0x0008: "enable_mask",  # one bit per excitation line
    0x000C: "imu_enable",
    0x0100: "frequency_base",  # 16 registers: phase increment of each excitation line's DDS
}


@dataclass
class TactileFrame:
    sequence: int
    timestamp_us: int
    impedance: np.ndarray  # complex64 (16,16)
    imu: np.ndarray | None = None  # float32 (n,6): accel m/s^2, gyro rad/s


@dataclass
class RegisterReply:
    address: int
    value: int
    status: int


def encode_blocks(values: np.ndarray) -> bytes:
    """Shared-exponent encoding of float values (length a multiple of 16)."""
    v = np.asarray(values, np.float64).reshape(-1, BLOCK)
    peak = np.abs(v).max(axis=1)
    # Smallest exponent with |mantissa| <= 127 for the block's peak.
    exp = np.where(peak > 0, np.ceil(np.log2(np.maximum(peak, 1e-300) / MANTISSA_MAX)), -128)
    exp = np.clip(exp, -128, 127).astype(np.int64)
    mant = np.clip(np.rint(v / np.exp2(exp)[:, None]), -MANTISSA_MAX, MANTISSA_MAX).astype("<i2")
    out = np.empty((v.shape[0], BLOCK_BYTES), np.uint8)
    out[:, 0] = exp.astype(np.int8).view(np.uint8)
    out[:, 1:] = mant.view(np.uint8).reshape(v.shape[0], 2 * BLOCK)
    return out.tobytes()


def decode_blocks(data: bytes, n_blocks: int) -> np.ndarray:
    raw = np.frombuffer(data, np.uint8, n_blocks * BLOCK_BYTES).reshape(n_blocks, BLOCK_BYTES)
    exp = raw[:, 0].view(np.int8).astype(np.float64)
    mant = np.ascontiguousarray(raw[:, 1:]).view("<i2").astype(np.float64)
    return (mant * np.exp2(exp)[:, None]).ravel()


def _split(impedance: np.ndarray) -> np.ndarray:
    z = np.asarray(impedance, np.complex128).reshape(ROWS * COLS)
    return np.concatenate([z.real, z.imag])


def quantize(impedance: np.ndarray) -> np.ndarray:
    """What survives the wire: encode and decode the matrix."""
    v = decode_blocks(encode_blocks(_split(impedance)), N_BLOCKS)
    return (v[: ROWS * COLS] + 1j * v[ROWS * COLS:]).reshape(ROWS, COLS).astype(np.complex64)


def encode_frame(f: TactileFrame) -> bytes:
    imu = np.zeros((0, 6)) if f.imu is None else np.asarray(f.imu, np.float64).reshape(-1, 6)
    if len(imu) > MAX_IMU:
        raise ValueError(f"at most {MAX_IMU} IMU samples per frame, got {len(imu)}")
    payload = FRAME_HEAD.pack(f.sequence & 0xFFFFFFFF, f.timestamp_us & 0xFFFFFFFFFFFFFFFF, len(imu))
    scale = np.array([ACCEL_LSB] * 3 + [GYRO_LSB] * 3)
    for sample in np.clip(np.rint(imu / scale), -32768, 32767).astype(int):
        payload += IMU_SAMPLE.pack(*sample)
    payload += encode_blocks(_split(f.impedance))
    return frame(TYPE_FRAME, payload)


def encode_write(address: int, value: int) -> bytes:
    return frame(TYPE_WRITE, REG.pack(address, value & 0xFFFFFFFF))


def encode_read(address: int) -> bytes:
    return frame(TYPE_READ, REG.pack(address, 0))


def encode_reply(address: int, value: int, status: int = 0) -> bytes:
    return frame(TYPE_REPLY, REPLY.pack(address, value & 0xFFFFFFFF, status))


class StreamDecoder:
    """Device bytes -> TactileFrame / RegisterReply. Never raises; ``stats`` counts what was rejected."""

    def __init__(self) -> None:
        self.frames = FrameDecoder(MAX_PAYLOAD, {TYPE_FRAME, TYPE_REPLY})
        self.stats = self.frames.stats
        self.stats.update({"sequence_gaps": 0, "malformed": 0})
        self.last_sequence: int | None = None

    def feed(self, data: bytes) -> list[TactileFrame | RegisterReply]:
        out: list[TactileFrame | RegisterReply] = []
        for kind, payload in self.frames.feed(data):
            try:
                item = _parse(kind, payload)
            except (ValueError, struct.error):
                self.stats["malformed"] += 1
                continue
            if isinstance(item, TactileFrame):
                if self.last_sequence is not None and item.sequence != (self.last_sequence + 1) & 0xFFFFFFFF:
                    self.stats["sequence_gaps"] += 1
                self.last_sequence = item.sequence
            out.append(item)
        return out


def _parse(kind: int, payload: bytes) -> TactileFrame | RegisterReply:
    if kind == TYPE_REPLY:
        return RegisterReply(*REPLY.unpack(payload))
    seq, ts, n_imu = FRAME_HEAD.unpack_from(payload)
    expected = FRAME_HEAD.size + n_imu * IMU_SAMPLE.size + N_BLOCKS * BLOCK_BYTES
    if n_imu > MAX_IMU or len(payload) != expected:
        raise ValueError(f"frame payload of {len(payload)} bytes, expected {expected}")
    imu = None
    off = FRAME_HEAD.size
    if n_imu:
        raw = np.array([IMU_SAMPLE.unpack_from(payload, off + i * IMU_SAMPLE.size) for i in range(n_imu)], float)
        imu = (raw * np.array([ACCEL_LSB] * 3 + [GYRO_LSB] * 3)).astype(np.float32)
        off += n_imu * IMU_SAMPLE.size
    v = decode_blocks(payload[off:], N_BLOCKS)
    z = (v[: ROWS * COLS] + 1j * v[ROWS * COLS:]).reshape(ROWS, COLS).astype(np.complex64)
    return TactileFrame(seq, ts, z, imu)
