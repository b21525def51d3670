"""The tactile readout protocol (glove readout module <-> host), version 2. Spec: docs/protocols/tactile.md.

Pure encode/decode, no I/O. A frame carries the complex matrix of the enabled lines only
(excitation mask x reception mask, row-major, real and imaginary part interleaved per cell) in
shared-exponent blocks (thesis 5.4): 16 values share one signed exponent byte and each has a
signed 16-bit mantissa, value = mantissa * 2**exponent. The rounding rules are integer-exact so
the FPGA packer (hdl/tactile) produces the same bytes from integer correlator sums.
"""

from __future__ import annotations

import functools
import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.protocols.framing import FrameDecoder, frame

ROWS = COLS = 16
BLOCK = 16
MANTISSA_MAX = 32767
EXP_MIN, EXP_MAX = -128, 111  # 32767 * 2**111 still fits float32
BLOCK_BYTES = 1 + 2 * BLOCK
ALL_LINES = 0xFFFF

TYPE_FRAME = 0x01
TYPE_REPLY = 0x02
TYPE_WRITE = 0x10
TYPE_READ = 0x11

# sequence, timestamp_us, tx_mask, rx_mask, status, imu count
FRAME_HEAD = struct.Struct("<IQHHBB")
IMU_SAMPLE = struct.Struct("<6h")  # ax ay az gx gy gz
ACCEL_LSB = 9.80665 / 2048.0  # m/s^2 per LSB (+-16 g)
GYRO_LSB = float(np.radians(2000.0) / 32768.0)  # rad/s per LSB (+-2000 dps)
IMU_SCALE = np.array([ACCEL_LSB] * 3 + [GYRO_LSB] * 3)
MAX_IMU = 8
REG = struct.Struct("<HI")  # address, value (value 0 in a read)
REPLY = struct.Struct("<HIB")  # address, value, status

# Frame status bits.
STATUS_ADC_OVERRANGE = 0x01  # a reception loop saturated during the window
STATUS_CONFIG_CHANGED = 0x02  # configuration written during the window: values mix two settings
STATUS_FRAME_DROPPED = 0x04  # the previous frame was not sent (link too slow): the sequence skips
STATUS_IMU_OVERFLOW = 0x08  # IMU samples were dropped

# Reply status.
REPLY_OK, REPLY_BAD_ADDRESS, REPLY_READ_ONLY = 0, 1, 2

DEVICE_ID = 0x58540002  # "XT", protocol version 2
REG_ID = 0x0000
REG_WINDOW = 0x0004  # ADC samples per correlation window (frame period = window * tick_div / f_clk)
REG_TX_ENABLE = 0x0008  # excitation lines driven and transmitted (bit per line)
REG_RX_ENABLE = 0x000C  # reception lines transmitted
REG_IMU_ENABLE = 0x0010
REG_CONTROL = 0x0014  # bit 0: run (stream frames)
REG_FRAME_COUNT = 0x0018  # read-only: sequence number of the last frame, all ones before the first
REG_TICK_DIV = 0x001C  # system clocks per ADC/DAC sample
CORE_CLOCK_HZ = 48_000_000  # the readout core's system clock (hdl/tactile)
REG_FREQ_BASE = 0x0100  # 16 registers, 4 bytes apart: DDS phase increment per excitation line
READ_ONLY = {REG_ID, REG_FRAME_COUNT}
REGISTER_NAMES = {REG_ID: "id", REG_WINDOW: "window", REG_TX_ENABLE: "tx_enable", REG_RX_ENABLE: "rx_enable",
                  REG_IMU_ENABLE: "imu_enable", REG_CONTROL: "control", REG_FRAME_COUNT: "frame_count",
                  REG_TICK_DIV: "tick_div", **{REG_FREQ_BASE + 4 * k: f"freq{k}" for k in range(16)}}
REGISTER_WIDTH = {REG_WINDOW: 16, REG_TX_ENABLE: 16, REG_RX_ENABLE: 16, REG_IMU_ENABLE: 1, REG_CONTROL: 1,
                  REG_TICK_DIV: 16}


class FrameError(ValueError):
    """A frame or command that cannot be encoded or decoded; the message says why."""


@dataclass
class TactileFrame:
    sequence: int
    timestamp_us: int
    impedance: np.ndarray  # complex64 (16,16); zeros outside the enabled lines
    imu: np.ndarray | None = None  # float32 (n,6): accel m/s^2, gyro rad/s
    tx_mask: int = ALL_LINES  # excitation lines (rows) carried in the frame
    rx_mask: int = ALL_LINES  # reception lines (columns) carried in the frame
    status: int = 0


@dataclass
class RegisterReply:
    address: int
    value: int
    status: int


@dataclass
class RegisterCommand:
    address: int
    value: int | None  # None: read


def lines(mask: int) -> np.ndarray:
    """Indices of the set bits of a 16-bit line mask."""
    return np.array([i for i in range(16) if mask >> i & 1], int)


def matrix_values(tx_mask: int, rx_mask: int) -> int:
    return 2 * bin(tx_mask & ALL_LINES).count("1") * bin(rx_mask & ALL_LINES).count("1")


def payload_bytes(tx_mask: int = ALL_LINES, rx_mask: int = ALL_LINES, n_imu: int = 0) -> int:
    n = matrix_values(tx_mask, rx_mask)
    return FRAME_HEAD.size + n_imu * IMU_SAMPLE.size + -(-n // BLOCK) + 2 * n


def frame_bytes(tx_mask: int = ALL_LINES, rx_mask: int = ALL_LINES, n_imu: int = 0) -> int:
    """Bytes on the wire for one frame, framing included."""
    return 9 + payload_bytes(tx_mask, rx_mask, n_imu)


MAX_PAYLOAD = payload_bytes(n_imu=MAX_IMU)


def block_exponents(values: np.ndarray) -> np.ndarray:
    """Per block of 16: the smallest exponent e with max|v| <= 32767 * 2**e (EXP_MIN for a zero block)."""
    v = np.asarray(values, np.float64)
    n_blocks = -(-len(v) // BLOCK)
    padded = np.zeros(n_blocks * BLOCK)
    padded[:len(v)] = v
    peak = np.abs(padded).reshape(n_blocks, BLOCK).max(axis=1)
    with np.errstate(divide="ignore"):
        e = np.ceil(np.log2(np.where(peak > 0, peak, 1.0) / MANTISSA_MAX)).astype(np.int64)
    # log2 may be off by one at exact powers of two: fix with exact comparisons.
    e += peak > np.ldexp(float(MANTISSA_MAX), e)
    e -= peak <= np.ldexp(float(MANTISSA_MAX), e - 1)
    return np.where(peak > 0, np.clip(e, EXP_MIN, EXP_MAX), EXP_MIN)


def encode_blocks(values: np.ndarray) -> bytes:
    """Shared-exponent blocks of a value sequence (the last block may hold fewer than 16)."""
    v = np.asarray(values, np.float64).ravel()
    if not np.all(np.isfinite(v)):
        raise FrameError("impedance contains NaN or infinity")
    exps = block_exponents(v)
    out = bytearray()
    for b, e in enumerate(exps):
        x = np.ldexp(v[b * BLOCK:(b + 1) * BLOCK], -int(e))
        fl = np.floor(x)
        mant = fl + (x - fl >= 0.5)  # round half up, as the FPGA's (v + 2**(e-1)) >>> e
        mant = np.clip(mant, -MANTISSA_MAX, MANTISSA_MAX).astype("<i2")
        out += struct.pack("<b", int(e)) + mant.tobytes()
    return bytes(out)


_FULL_BLOCK = np.dtype([("e", "i1"), ("m", "<i2", (BLOCK,))])  # packed: 1 + 2 x 16 bytes


def decode_blocks(data: bytes, n_values: int) -> np.ndarray:
    """Inverse of encode_blocks for n_values values; FrameError on a short buffer or bad exponent.
    Whole blocks are read in one structured view (this runs per frame at 1 kHz per glove)."""
    n_full, rest = divmod(n_values, BLOCK)
    need = n_full * _FULL_BLOCK.itemsize + (1 + 2 * rest if rest else 0)
    if need > len(data):
        raise FrameError("matrix blocks truncated")
    blocks = np.frombuffer(data, _FULL_BLOCK, n_full)
    exps = blocks["e"].astype(np.int64)
    mant = blocks["m"].astype(np.float64)
    if rest:
        off = n_full * _FULL_BLOCK.itemsize
        exps = np.append(exps, np.frombuffer(data, "i1", 1, off).astype(np.int64))
        tail = np.zeros((1, BLOCK))
        tail[0, :rest] = np.frombuffer(data, "<i2", rest, off + 1)
        mant = np.concatenate([mant.reshape(-1, BLOCK), tail])
    if len(exps) and exps.max() > EXP_MAX:
        raise FrameError(f"block exponent {int(exps.max())} above {EXP_MAX}")
    return np.ldexp(mant.reshape(-1, BLOCK), exps[:, None]).ravel()[:n_values]


def _cells(impedance: np.ndarray, tx_mask: int, rx_mask: int) -> np.ndarray:
    z = np.asarray(impedance)
    if z.shape != (ROWS, COLS):
        raise FrameError(f"impedance must be (16,16), got {z.shape}")
    sel = z[np.ix_(lines(tx_mask), lines(rx_mask))].ravel()
    return np.stack([sel.real, sel.imag], axis=1).ravel().astype(np.float64)


@functools.lru_cache(maxsize=64)
def cell_index(tx_mask: int, rx_mask: int) -> np.ndarray:
    """Flat indices of the carried cells in row-major order (cached: masks rarely change)."""
    return (lines(tx_mask)[:, None] * COLS + lines(rx_mask)[None, :]).ravel()


def _matrix(values: np.ndarray, tx_mask: int, rx_mask: int) -> np.ndarray:
    z = np.zeros(ROWS * COLS, np.complex64)
    z[cell_index(tx_mask, rx_mask)] = values[0::2] + 1j * values[1::2]
    return z.reshape(ROWS, COLS)


def quantize(impedance: np.ndarray, tx_mask: int = ALL_LINES, rx_mask: int = ALL_LINES) -> np.ndarray:
    """What survives the wire: encode and decode the matrix (zeros outside the masks)."""
    v = _cells(impedance, tx_mask, rx_mask)
    return _matrix(decode_blocks(encode_blocks(v), len(v)), tx_mask, rx_mask)


def encode_frame(f: TactileFrame) -> bytes:
    """Frame bytes; FrameError on a bad shape, too many IMU samples or non-finite values."""
    imu = np.zeros((0, 6)) if f.imu is None else np.asarray(f.imu, np.float64).reshape(-1, 6)
    if len(imu) > MAX_IMU:
        raise FrameError(f"at most {MAX_IMU} IMU samples per frame, got {len(imu)}")
    tx, rx = f.tx_mask & ALL_LINES, f.rx_mask & ALL_LINES
    payload = FRAME_HEAD.pack(f.sequence & 0xFFFFFFFF, f.timestamp_us & 0xFFFFFFFFFFFFFFFF, tx, rx,
                              f.status & 0xFF, len(imu))
    for sample in np.clip(np.rint(imu / IMU_SCALE), -32768, 32767).astype(int):
        payload += IMU_SAMPLE.pack(*sample)
    payload += encode_blocks(_cells(f.impedance, tx, rx))
    return frame(TYPE_FRAME, payload)


def encode_command(address: int, value: int | None = None) -> bytes:
    """Host -> device: register write (value given) or read (value None)."""
    if not 0 <= address <= 0xFFFF:
        raise FrameError(f"register address {address:#x} outside 16 bits")
    if value is None:
        return frame(TYPE_READ, REG.pack(address, 0))
    return frame(TYPE_WRITE, REG.pack(address, value & 0xFFFFFFFF))


def encode_write(address: int, value: int) -> bytes:
    return encode_command(address, value)


def encode_read(address: int) -> bytes:
    return encode_command(address)


def encode_reply(address: int, value: int, status: int = REPLY_OK) -> bytes:
    """Device -> host: the register's value after the command, and a status."""
    return frame(TYPE_REPLY, REPLY.pack(address & 0xFFFF, value & 0xFFFFFFFF, status & 0xFF))


def decode_reply(data: bytes) -> RegisterReply:
    """Exactly one reply frame -> RegisterReply; FrameError otherwise."""
    dec = StreamDecoder()
    items = dec.feed(data)
    if len(items) != 1 or not isinstance(items[0], RegisterReply) or dec.stats["bytes_discarded"]:
        raise FrameError(f"not one register reply frame ({len(data)} bytes, decoder {dec.stats})")
    return items[0]


class StreamDecoder:
    """Device bytes -> TactileFrame / RegisterReply. Never raises; ``stats`` counts what was rejected.

    stats: frames, crc_errors, resyncs, bytes_discarded, oversize, unknown_type (framing layer),
    frame_bytes (bytes in good frames), malformed / malformed_bytes (CRC-valid frames whose payload
    is inconsistent), sequence_gaps (events) and frames_lost (missing sequence numbers).
    """

    def __init__(self) -> None:
        self.frames = FrameDecoder(MAX_PAYLOAD, {TYPE_FRAME, TYPE_REPLY})
        self.stats = self.frames.stats
        self.stats.update({"sequence_gaps": 0, "frames_lost": 0, "malformed": 0, "malformed_bytes": 0})
        self.last_sequence: int | None = None

    def feed(self, data: bytes) -> list[TactileFrame | RegisterReply]:
        out: list[TactileFrame | RegisterReply] = []
        for kind, payload in self.frames.feed(bytes(data)):
            try:
                item = _parse(kind, payload)
            except (FrameError, struct.error):
                self.stats["malformed"] += 1
                self.stats["malformed_bytes"] += len(payload) + 9
                continue
            if isinstance(item, TactileFrame):
                if self.last_sequence is not None:
                    missing = (item.sequence - self.last_sequence - 1) & 0xFFFFFFFF
                    if missing:
                        self.stats["sequence_gaps"] += 1
                        self.stats["frames_lost"] += missing if missing < 1 << 31 else 0
                self.last_sequence = item.sequence
            out.append(item)
        return out


def _parse(kind: int, payload: bytes) -> TactileFrame | RegisterReply:
    if kind == TYPE_REPLY:
        if len(payload) != REPLY.size:
            raise FrameError(f"reply payload of {len(payload)} bytes, expected {REPLY.size}")
        return RegisterReply(*REPLY.unpack(payload))
    seq, ts, tx, rx, status, n_imu = FRAME_HEAD.unpack_from(payload)
    if n_imu > MAX_IMU:
        raise FrameError(f"{n_imu} IMU samples, at most {MAX_IMU}")
    expected = payload_bytes(tx, rx, n_imu)
    if len(payload) != expected:
        raise FrameError(f"frame payload of {len(payload)} bytes, expected {expected}")
    off = FRAME_HEAD.size
    imu = None
    if n_imu:
        raw = np.frombuffer(payload, "<i2", 6 * n_imu, off).reshape(n_imu, 6)
        imu = (raw * IMU_SCALE).astype(np.float32)
        off += n_imu * IMU_SAMPLE.size
    values = decode_blocks(payload[off:], matrix_values(tx, rx))
    return TactileFrame(seq, ts, _matrix(values, tx, rx), imu, tx, rx, status)


class CommandDecoder:
    """Device side: host bytes -> RegisterCommand (for simulated modules). Never raises."""

    def __init__(self) -> None:
        self.frames = FrameDecoder(REG.size, {TYPE_WRITE, TYPE_READ})
        self.stats = self.frames.stats
        self.stats["malformed"] = 0

    def feed(self, data: bytes) -> list[RegisterCommand]:
        out = []
        for kind, payload in self.frames.feed(bytes(data)):
            if len(payload) != REG.size:
                self.stats["malformed"] += 1
                continue
            address, value = REG.unpack(payload)
            out.append(RegisterCommand(address, value if kind == TYPE_WRITE else None))
        return out


def default_registers() -> dict[int, int]:
    """Power-on register values of the readout core (hdl/tactile/tactile_regs.v has the same)."""
    regs = {REG_ID: DEVICE_ID, REG_WINDOW: 256, REG_TX_ENABLE: ALL_LINES, REG_RX_ENABLE: ALL_LINES,
            REG_IMU_ENABLE: 0, REG_CONTROL: 1, REG_FRAME_COUNT: 0xFFFFFFFF, REG_TICK_DIV: 256}
    for k in range(16):  # line k at (8 + 2k) cycles per default 256-sample window: orthogonal over it
        regs[REG_FREQ_BASE + 4 * k] = (8 + 2 * k) << 24
    return regs


class RegisterFile:
    """Reference model of the register semantics (the simulated module and the HDL tests use it)."""

    def __init__(self) -> None:
        self.values = default_registers()

    def handle(self, cmd: RegisterCommand) -> RegisterReply:
        if cmd.address not in self.values:
            return RegisterReply(cmd.address, 0, REPLY_BAD_ADDRESS)
        if cmd.value is not None:
            if cmd.address in READ_ONLY:
                return RegisterReply(cmd.address, self.values[cmd.address], REPLY_READ_ONLY)
            width = REGISTER_WIDTH.get(cmd.address, 32)
            self.values[cmd.address] = cmd.value & ((1 << width) - 1)
        return RegisterReply(cmd.address, self.values[cmd.address], REPLY_OK)


VECTORS_PATH = Path(__file__).parent / "vectors" / "tactile.json"


def make_vectors() -> list[dict]:
    """Test vectors: integer-valued matrices (what the FPGA correlator produces), several masks."""
    rng = np.random.default_rng(7)
    cases: list[dict] = []
    glove_rx = 0x003F
    specs = [(ALL_LINES, ALL_LINES, 1e3, None, 0), (ALL_LINES, glove_rx, 2e6, None, 0),
             (0x0F0F, 0x8001, 1.0, 1, STATUS_ADC_OVERRANGE), (0x0007, 0x0013, 30.0, None, 0)]
    for i, (tx, rx, scale, n_imu, status) in enumerate(specs):
        z = np.zeros((16, 16), np.complex128)
        rows, cols = lines(tx), lines(rx)
        block = rng.normal(0, scale, (len(rows), len(cols), 2)) * rng.choice([1, 1e-3, 0], (len(rows), 1, 1))
        block = np.clip(np.round(block), -(2**23), 2**23)  # exact in float32
        z[np.ix_(rows, cols)] = block[..., 0] + 1j * block[..., 1]
        if i == 1:
            z[0, :] = 0  # an all-zero block: exponent -128
        imu = None if n_imu is None else np.array([[0.0, 0.0, 9.81, 0.01, -0.02, 0.5]], np.float32)
        frame_ = TactileFrame(1000 + i, 123_456_789 + 1000 * i, z.astype(np.complex64), imu, tx, rx, status)
        cases.append({"sequence": frame_.sequence, "timestamp_us": frame_.timestamp_us, "tx_mask": tx,
                      "rx_mask": rx, "status": status, "real": z.real.astype(int).ravel().tolist(),
                      "imag": z.imag.astype(int).ravel().tolist(),
                      "imu": None if imu is None else imu.tolist(), "bytes": encode_frame(frame_).hex()})
    cases.append({"register_write": [REG_WINDOW, 4096], "bytes": encode_write(REG_WINDOW, 4096).hex()})
    cases.append({"register_read": [REG_ID], "bytes": encode_read(REG_ID).hex()})
    cases.append({"register_reply": [REG_ID, DEVICE_ID, 0], "bytes": encode_reply(REG_ID, DEVICE_ID).hex()})
    return cases


if __name__ == "__main__":  # regenerate only when the protocol changes on purpose
    VECTORS_PATH.write_text(json.dumps(make_vectors(), indent=1) + "\n")
