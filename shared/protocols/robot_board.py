"""The robot control-board protocol, version 3 (host <-> board). Spec: docs/protocols/robot_board.md.

Host -> board: a command frame per control tick (mode and setpoints per joint), or a plan frame (the
same command plus the setpoints of the next few tens of milliseconds, which the board plays while
the host is late), and a config frame
(watchdog timeout, per-joint limits) at start-up and then about once a second as a heartbeat.
Board -> host: feedback frames (positions, velocities, motor currents, watchdog state, board time).
Framing (sync, type, length, CRC-32) is shared/protocols/framing.py; every payload of this protocol
starts with a u32 sequence number. Pure encode/decode: no I/O.

Regenerate the test vectors (only when the protocol changes on purpose):
``python -m shared.protocols.robot_board``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from shared.protocols.framing import FrameDecoder, frame
from shared.robots.registry import DEFAULT_ROBOT, describe

VERSION = 3
TYPE_COMMAND = 0x20
TYPE_FEEDBACK = 0x21
TYPE_CONFIG = 0x22
TYPE_PLAN = 0x23
MAX_JOINTS = 32
MAX_KNOTS = 16  # a plan's setpoints, the command's own included
DEFAULT_WATCHDOG_US = 10_000

# The default robot's joints in board-channel order (shared/robots): the test vectors' layout.
JOINTS = describe(DEFAULT_ROBOT).board_order


class Mode(IntEnum):
    BRAKE = 0  # windings shorted: strong damping, no drive (also what the watchdog does)
    POSITION = 1  # PID on position, velocity as feed-forward, effort as feed-forward
    VELOCITY = 2  # PI on velocity, effort as feed-forward
    EFFORT = 3  # effort (N or N m) straight to the current loop
    IMPEDANCE = 4  # effort = stiffness*(q_d - q) + damping*(qd_d - qd) + effort_ff
    PNEUMATIC = 5  # position is the target of the two-stage muscle-pressure PID (hand-arm fingers only)


# Feedback flags (u16).
WATCHDOG_EXPIRED = 0x0001  # no command within the timeout: every axis brakes
NO_COMMAND_YET = 0x0002  # no valid command since power-up (also braking)
LIMITS_ACTIVE = 0x0004  # a config frame with limits is applied
CLAMPED = 0x0008  # the board clamped a setpoint or effort during the last tick (see joint_flags)
COMMAND_REJECTED = 0x0010  # the last command frame was refused (joint count or non-finite values)
CONFIG_REJECTED = 0x0020  # the last config frame was refused (joint count, ordering, non-finite)

# Per-joint flags (u8).
JOINT_POSITION_LIMIT = 0x01
JOINT_VELOCITY_LIMIT = 0x02
JOINT_EFFORT_LIMIT = 0x04
JOINT_NON_FINITE = 0x08  # this joint's setpoint was not finite: the board holds the last safe one
JOINT_BRAKING = 0x10

CMD_HEAD = struct.Struct("<IB")  # sequence, joint count
CMD_JOINT = np.dtype([("mode", "u1"), ("position", "<f4"), ("velocity", "<f4"), ("effort", "<f4"),
                      ("stiffness", "<f4"), ("damping", "<f4")])  # packed: 21 bytes
# sequence, time us, last command arrival us, last command sequence, config sequence, flags, n
FB_HEAD = struct.Struct("<IQQIIHB")
FB_JOINT = np.dtype([("position", "<f4"), ("velocity", "<f4"), ("current", "<f4"), ("flags", "u1")])  # 13 B
CFG_HEAD = struct.Struct("<IIB")  # sequence, watchdog timeout us, joint count (0: no limits)
CFG_JOINT = np.dtype([("lower", "<f4"), ("upper", "<f4"), ("velocity", "<f4"), ("effort", "<f4")])  # 16 B
PLAN_HEAD = struct.Struct("<IBBH")  # sequence, joint count, knot count, knot spacing us
PLAN_KNOT = np.dtype([("position", "<f4"), ("velocity", "<f4")])  # 8 B per joint and later knot
MAX_PAYLOAD = max(PLAN_HEAD.size + MAX_JOINTS * CMD_JOINT.itemsize + (MAX_KNOTS - 1) * MAX_JOINTS * PLAN_KNOT.itemsize,
                  FB_HEAD.size + MAX_JOINTS * FB_JOINT.itemsize,
                  CFG_HEAD.size + MAX_JOINTS * CFG_JOINT.itemsize)


class FrameError(ValueError):
    """A frame whose CRC is good but whose payload is not a valid message; the message says why."""


@dataclass
class JointCommand:
    """One joint's command. Units: m, rad, N, N m; stiffness N/m or N m/rad, damping N s/m or N m s/rad."""

    mode: Mode = Mode.BRAKE
    position: float = 0.0
    velocity: float = 0.0
    effort: float = 0.0
    stiffness: float = 0.0
    damping: float = 0.0


@dataclass
class CommandFrame:
    sequence: int
    mode: np.ndarray  # (n,) uint8 Mode
    position: np.ndarray  # (n,) float
    velocity: np.ndarray
    effort: np.ndarray
    stiffness: np.ndarray
    damping: np.ndarray

    @property
    def n(self) -> int:
        return len(self.mode)

    @classmethod
    def from_joints(cls, sequence: int, joints: list[JointCommand]) -> CommandFrame:
        col = [np.array([getattr(j, f) for j in joints], float) for f in CMD_JOINT.names[1:]]
        return cls(sequence, np.array([int(j.mode) for j in joints], np.uint8), *col)

    @classmethod
    def hold(cls, sequence: int, position: np.ndarray) -> CommandFrame:
        """Position mode at ``position``, zero feed-forward."""
        p = np.asarray(position, float)
        z = np.zeros(len(p))
        mode = np.full(len(p), Mode.POSITION, np.uint8)
        return cls(sequence, mode, p.copy(), z, z.copy(), z.copy(), z.copy())

    @classmethod
    def brake(cls, sequence: int, n: int) -> CommandFrame:
        z = np.zeros(n)
        return cls(sequence, np.zeros(n, np.uint8), z, z.copy(), z.copy(), z.copy(), z.copy())

    def joint(self, i: int) -> JointCommand:
        return JointCommand(Mode(int(self.mode[i])), float(self.position[i]), float(self.velocity[i]),
                            float(self.effort[i]), float(self.stiffness[i]), float(self.damping[i]))

    def copy(self) -> CommandFrame:
        return CommandFrame(self.sequence, *(np.array(getattr(self, f), copy=True) for f in CMD_JOINT.names))


@dataclass
class PlanFrame:
    """A command (knot 0, in force from the frame's arrival) and the positions and velocities of the
    next ``knots - 1`` setpoints, ``spacing_us`` apart; modes, efforts and gains hold for all of them.
    The board moves through the knots by linear interpolation and holds the last one; its watchdog
    counts from the last knot's time (docs/protocols/robot_board.md, "Plans")."""

    command: CommandFrame
    position: np.ndarray  # (knots - 1, n): the later knots
    velocity: np.ndarray
    spacing_us: int

    @property
    def sequence(self) -> int:
        return self.command.sequence

    @property
    def n(self) -> int:
        return self.command.n

    @property
    def knots(self) -> int:
        return 1 + len(self.position)

    @property
    def span_s(self) -> float:
        """From the first knot to the last."""
        return (self.knots - 1) * self.spacing_us * 1e-6

    def at(self, dt: float) -> CommandFrame:
        """The command ``dt`` seconds after knot 0: positions and velocities interpolated between the
        knots around it, the last knot's after the end (the frame's own command before knot 0)."""
        if dt <= 0 or not len(self.position):
            return self.command
        x = dt / (self.spacing_us * 1e-6)
        k = int(x)
        if k >= len(self.position):
            p, v = self.position[-1], self.velocity[-1]
        else:
            p0 = self.command.position if k == 0 else self.position[k - 1]
            v0 = self.command.velocity if k == 0 else self.velocity[k - 1]
            s = x - k
            p = p0 + s * (self.position[k] - p0)
            v = v0 + s * (self.velocity[k] - v0)
        c = self.command
        return CommandFrame(c.sequence, c.mode, p, v, c.effort, c.stiffness, c.damping)


@dataclass
class FeedbackFrame:
    sequence: int
    timestamp_us: int  # board clock at the sample
    flags: int
    position: np.ndarray  # (n,) m or rad, from the absolute encoders
    velocity: np.ndarray
    current: np.ndarray  # (n,) motor current, A (q-axis)
    last_command_us: int = 0  # board time the last command frame arrived (0: none yet)
    last_command_sequence: int = 0  # that frame's sequence number
    config_sequence: int = 0  # sequence of the config frame the board runs with (0: defaults)
    joint_flags: np.ndarray | None = None  # (n,) uint8 JOINT_* bits; None encodes as zeros

    @property
    def watchdog_expired(self) -> bool:
        return bool(self.flags & WATCHDOG_EXPIRED)


@dataclass
class ConfigFrame:
    """Watchdog timeout and (optionally) per-joint limits; the host repeats it as a heartbeat."""

    watchdog_timeout_us: int = DEFAULT_WATCHDOG_US
    lower: np.ndarray | None = None  # (n,) position limits; all four arrays or none
    upper: np.ndarray | None = None
    velocity: np.ndarray | None = None  # (n,) |velocity| maximum
    effort: np.ndarray | None = None  # (n,) |effort| maximum
    sequence: int = 0

    @property
    def has_limits(self) -> bool:
        return self.lower is not None


Message = CommandFrame | PlanFrame | FeedbackFrame | ConfigFrame


def _rows(dtype: np.dtype, n: int, **cols) -> bytes:
    rows = np.zeros(n, dtype)
    for name, values in cols.items():
        v = np.asarray(values)
        if v.shape != (n,):
            raise FrameError(f"{name} has shape {v.shape}, expected ({n},)")
        rows[name] = v
    return rows.tobytes()


def _check_count(n: int) -> None:
    if n > MAX_JOINTS:
        raise FrameError(f"{n} joints, at most {MAX_JOINTS}")


def encode_command(c: CommandFrame) -> bytes:
    n = len(c.mode)
    _check_count(n)
    body = _rows(CMD_JOINT, n, **{f: getattr(c, f) for f in CMD_JOINT.names})
    return frame(TYPE_COMMAND, CMD_HEAD.pack(c.sequence & 0xFFFFFFFF, n) + body)


def encode_plan(p: PlanFrame) -> bytes:
    c = p.command
    n = len(c.mode)
    _check_count(n)
    if not 1 <= p.knots <= MAX_KNOTS:
        raise FrameError(f"{p.knots} knots, 1 to {MAX_KNOTS}")
    if np.shape(p.position) != (p.knots - 1, n) or np.shape(p.velocity) != (p.knots - 1, n):
        raise FrameError(f"plan knots have shapes {np.shape(p.position)} and {np.shape(p.velocity)}, "
                         f"expected ({p.knots - 1}, {n})")
    if not 1 <= p.spacing_us <= 0xFFFF:
        raise FrameError(f"knot spacing {p.spacing_us} us outside 1 .. 65535")
    body = _rows(CMD_JOINT, n, **{f: getattr(c, f) for f in CMD_JOINT.names})
    knots = np.zeros((p.knots - 1, n), PLAN_KNOT)
    knots["position"], knots["velocity"] = p.position, p.velocity
    head = PLAN_HEAD.pack(c.sequence & 0xFFFFFFFF, n, p.knots, p.spacing_us)
    return frame(TYPE_PLAN, head + body + knots.tobytes())


def encode_feedback(f: FeedbackFrame) -> bytes:
    n = len(f.position)
    _check_count(n)
    jf = np.zeros(n, np.uint8) if f.joint_flags is None else f.joint_flags
    head = FB_HEAD.pack(f.sequence & 0xFFFFFFFF, f.timestamp_us, f.last_command_us,
                        f.last_command_sequence & 0xFFFFFFFF, f.config_sequence & 0xFFFFFFFF,
                        f.flags & 0xFFFF, n)
    return frame(TYPE_FEEDBACK, head + _rows(FB_JOINT, n, position=f.position, velocity=f.velocity,
                                             current=f.current, flags=jf))


def encode_config(c: ConfigFrame) -> bytes:
    arrays = (c.lower, c.upper, c.velocity, c.effort)
    if any(a is None for a in arrays) and not all(a is None for a in arrays):
        raise FrameError("config limits: give lower, upper, velocity and effort together, or none")
    n = 0 if c.lower is None else len(c.lower)
    _check_count(n)
    body = b"" if n == 0 else _rows(CFG_JOINT, n, lower=c.lower, upper=c.upper, velocity=c.velocity,
                                    effort=c.effort)
    return frame(TYPE_CONFIG, CFG_HEAD.pack(c.sequence & 0xFFFFFFFF, c.watchdog_timeout_us, n) + body)


def encode(msg: Message) -> bytes:
    if isinstance(msg, CommandFrame):
        return encode_command(msg)
    if isinstance(msg, PlanFrame):
        return encode_plan(msg)
    if isinstance(msg, FeedbackFrame):
        return encode_feedback(msg)
    if isinstance(msg, ConfigFrame):
        return encode_config(msg)
    raise TypeError(f"not a robot-board message: {type(msg).__name__}")


def _table(p: bytes, head: struct.Struct, n: int, dtype: np.dtype, what: str) -> np.ndarray:
    _check_count(n)
    if len(p) != head.size + n * dtype.itemsize:
        want = head.size + n * dtype.itemsize
        raise FrameError(f"{what}: {len(p)} payload bytes, {want} expected for {n} joints")
    return np.frombuffer(p, dtype, n, head.size)


def decode_payload(kind: int, p: bytes) -> Message:
    """One frame's payload (CRC already checked) -> message. Raises FrameError."""
    if kind == TYPE_COMMAND:
        if len(p) < CMD_HEAD.size:
            raise FrameError(f"command: {len(p)} payload bytes, shorter than its header")
        seq, n = CMD_HEAD.unpack_from(p)
        t = _table(p, CMD_HEAD, n, CMD_JOINT, "command")
        return CommandFrame(seq, t["mode"].copy(), *(t[f].astype(float) for f in CMD_JOINT.names[1:]))
    if kind == TYPE_PLAN:
        return _decode_plan(p)
    if kind == TYPE_FEEDBACK:
        if len(p) < FB_HEAD.size:
            raise FrameError(f"feedback: {len(p)} payload bytes, shorter than its header")
        seq, ts, last_us, last_seq, cfg_seq, flags, n = FB_HEAD.unpack_from(p)
        t = _table(p, FB_HEAD, n, FB_JOINT, "feedback")
        return FeedbackFrame(seq, ts, flags, t["position"].astype(float), t["velocity"].astype(float),
                             t["current"].astype(float), last_us, last_seq, cfg_seq, t["flags"].copy())
    if kind == TYPE_CONFIG:
        if len(p) < CFG_HEAD.size:
            raise FrameError(f"config: {len(p)} payload bytes, shorter than its header")
        seq, timeout, n = CFG_HEAD.unpack_from(p)
        t = _table(p, CFG_HEAD, n, CFG_JOINT, "config")
        lim = [t[f].astype(float) for f in CFG_JOINT.names] if n else [None] * 4
        return ConfigFrame(timeout, *lim, sequence=seq)
    raise FrameError(f"unknown frame type 0x{kind:02x}")


def _decode_plan(p: bytes) -> PlanFrame:
    if len(p) < PLAN_HEAD.size:
        raise FrameError(f"plan: {len(p)} payload bytes, shorter than its header")
    seq, n, knots, spacing = PLAN_HEAD.unpack_from(p)
    _check_count(n)
    if not 1 <= knots <= MAX_KNOTS or spacing == 0:
        raise FrameError(f"plan: {knots} knots {spacing} us apart (1 to {MAX_KNOTS} knots, spacing > 0)")
    want = PLAN_HEAD.size + n * CMD_JOINT.itemsize + (knots - 1) * n * PLAN_KNOT.itemsize
    if len(p) != want:
        raise FrameError(f"plan: {len(p)} payload bytes, {want} expected for {n} joints and {knots} knots")
    t = np.frombuffer(p, CMD_JOINT, n, PLAN_HEAD.size)
    later = np.frombuffer(p, PLAN_KNOT, (knots - 1) * n, PLAN_HEAD.size + n * CMD_JOINT.itemsize).reshape(knots - 1, n)
    command = CommandFrame(seq, t["mode"].copy(), *(t[f].astype(float) for f in CMD_JOINT.names[1:]))
    return PlanFrame(command, later["position"].astype(float), later["velocity"].astype(float), spacing)


def decode(data: bytes) -> Message:
    """Exactly one complete frame -> message. Raises FrameError (use StreamDecoder for streams)."""
    d = StreamDecoder()
    msgs = d.feed(data)
    if len(msgs) != 1 or len(d.frames.buffer) or d.stats["bytes_discarded"]:
        raise FrameError(d.last_error or f"expected one frame, got {len(msgs)} and "
                                          f"{d.stats['bytes_discarded'] + len(d.frames.buffer)} stray bytes")
    return msgs[0]


class StreamDecoder:
    """Bytes -> messages of either direction. Never raises; ``stats`` counts every rejection.

    stats: frames, crc_errors, resyncs, bytes_discarded, oversize, unknown_type, frame_bytes (framing),
    malformed (good CRC, bad payload), sequence_gaps (per frame type), frames_lost (numbers skipped).
    """

    def __init__(self) -> None:
        self.frames = FrameDecoder(MAX_PAYLOAD, {TYPE_COMMAND, TYPE_PLAN, TYPE_FEEDBACK, TYPE_CONFIG})
        self.stats = self.frames.stats
        self.stats.update({"sequence_gaps": 0, "frames_lost": 0, "malformed": 0})
        self.last_error = ""
        self._last: dict[int, int] = {}

    def feed(self, data: bytes) -> list[Message]:
        out: list[Message] = []
        before = self.stats["crc_errors"]
        for kind, payload in self.frames.feed(data):
            try:
                msg = decode_payload(kind, payload)
            except FrameError as exc:
                self.stats["malformed"] += 1
                self.last_error = str(exc)
                continue
            kind = TYPE_COMMAND if kind == TYPE_PLAN else kind  # commands and plans share one sequence
            last = self._last.get(kind)
            if last is not None and msg.sequence != (last + 1) & 0xFFFFFFFF:
                self.stats["sequence_gaps"] += 1
                missing = (msg.sequence - last - 1) & 0xFFFFFFFF
                if missing < 0x80000000:  # a restart (sequence back to 0) is a gap, not 4e9 losses
                    self.stats["frames_lost"] += missing
            self._last[kind] = msg.sequence
            out.append(msg)
        if self.stats["crc_errors"] > before:
            self.last_error = "CRC mismatch"
        return out


def _f32(a) -> list[float]:
    """Values that survive the float32 wire exactly, so vectors compare with ==."""
    return np.asarray(a, np.float32).astype(float).tolist()


def vector_cases() -> list[dict]:
    """The committed test vectors (shared/protocols/vectors/robot_board.json)."""
    n = len(JOINTS)
    cases = []
    cmd = CommandFrame(42, np.array([1] * 9 + [4], np.uint8), np.array(_f32(np.linspace(-0.1, 0.1, n))),
                       np.zeros(n), np.full(n, 0.5), np.full(n, 100.0), np.full(n, 5.0))
    mixed = CommandFrame.from_joints(0xFFFFFFFF, [
        JointCommand(Mode(k % len(Mode)), *_f32([0.01 * k, -0.125 * k, 2.5 - k, 50.0 * k, 0.25 * k]))
        for k in range(n)])
    for c in (cmd, mixed):
        fields = {f: getattr(c, f).tolist() for f in CMD_JOINT.names}
        cases.append({"command": {"sequence": c.sequence, **fields},
                      "bytes": encode_command(c).hex()})
    later = np.array(_f32(np.linspace(0.0, 0.05, 2 * n))).reshape(2, n)
    plan = PlanFrame(cmd, later, -later, 8000)
    cases.append({"plan": {"sequence": plan.sequence, "spacing_us": plan.spacing_us,
                           "command": {f: getattr(cmd, f).tolist() for f in CMD_JOINT.names},
                           "position": later.tolist(), "velocity": (-later).tolist()},
                  "bytes": encode_plan(plan).hex()})
    fbs = [FeedbackFrame(7, 1_000_000, WATCHDOG_EXPIRED, np.array(_f32(np.linspace(0, 0.3, n))),
                         np.full(n, -0.25), np.full(n, 1.5), 989_000, 41, 0),
           FeedbackFrame(123_456, 2 ** 40 + 5, WATCHDOG_EXPIRED | LIMITS_ACTIVE | CLAMPED,
                         np.array(_f32(np.arange(n) * 0.015625)), np.array(_f32(np.arange(n) * -0.5)),
                         np.array(_f32(np.arange(n) * 0.75)), 2 ** 40 - 10_000, 77, 3,
                         np.array([0, 1, 2, 4, 8, 16, 0, 0, 3, 0], np.uint8))]
    for f in fbs:
        cases.append({"feedback": {"sequence": f.sequence, "timestamp_us": f.timestamp_us, "flags": f.flags,
                                   "last_command_us": f.last_command_us,
                                   "last_command_sequence": f.last_command_sequence,
                                   "config_sequence": f.config_sequence,
                                   "position": f.position.tolist(), "velocity": f.velocity.tolist(),
                                   "current": f.current.tolist(),
                                   "joint_flags": f.joint_flags.tolist() if f.joint_flags is not None
                                   else [0] * n},
                      "bytes": encode_feedback(f).hex()})
    cfgs = [ConfigFrame(10_000),
            ConfigFrame(10_000, np.array(_f32([-0.3] * n)), np.array(_f32([0.3] * n)),
                        np.array(_f32([0.5] * n)), np.array(_f32([200.0] * n)), sequence=3)]
    for c in cfgs:
        lim = {f: None if getattr(c, f) is None else getattr(c, f).tolist() for f in CFG_JOINT.names}
        cases.append({"config": {"sequence": c.sequence, "watchdog_timeout_us": c.watchdog_timeout_us, **lim},
                      "bytes": encode_config(c).hex()})
    return cases


if __name__ == "__main__":
    import json
    from pathlib import Path

    out = Path(__file__).parent / "vectors" / "robot_board.json"
    out.write_text(json.dumps(vector_cases(), indent=1) + "\n")
    print(f"wrote {out}")
