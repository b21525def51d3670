"""The robot control-board protocol (host <-> board). Spec: docs/protocols/robot_board.md.

Host -> board: a command frame per control tick with a mode and setpoints per joint; a config
frame (watchdog timeout). Board -> host: feedback frames with positions, velocities, motor
currents and the watchdog state. Framing (sync, type, length, CRC-32) as shared/protocols/framing.py.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from shared.protocols.framing import FrameDecoder, frame

TYPE_COMMAND = 0x20
TYPE_FEEDBACK = 0x21
TYPE_CONFIG = 0x22
MAX_JOINTS = 32


class Mode(IntEnum):
    BRAKE = 0  # windings shorted: strong damping, no drive (also what the watchdog does)
    POSITION = 1
    VELOCITY = 2
    EFFORT = 3
    IMPEDANCE = 4  # effort = stiffness*(q_d - q) + damping*(qd_d - qd) + effort_ff


WATCHDOG_EXPIRED = 0x01
CMD_HEAD = struct.Struct("<IB")  # sequence, joint count
CMD_JOINT = struct.Struct("<B5f")  # mode, position, velocity, effort, stiffness, damping
FB_HEAD = struct.Struct("<IQQBB")  # sequence, board time us, last command's arrival us, flags, joint count
FB_JOINT = struct.Struct("<3f")  # position, velocity, motor current (A)
CONFIG = struct.Struct("<I")  # watchdog timeout in microseconds
MAX_PAYLOAD = CMD_HEAD.size + MAX_JOINTS * CMD_JOINT.size


@dataclass
class CommandFrame:
    sequence: int
    mode: np.ndarray  # (n,) uint8 Mode
    position: np.ndarray  # (n,) float
    velocity: np.ndarray
    effort: np.ndarray
    stiffness: np.ndarray
    damping: np.ndarray


@dataclass
class FeedbackFrame:
    sequence: int
    timestamp_us: int
    flags: int
    position: np.ndarray
    velocity: np.ndarray
    current: np.ndarray
    last_command_us: int = 0  # board time the last command frame arrived (0: none yet)

    @property
    def watchdog_expired(self) -> bool:
        return bool(self.flags & WATCHDOG_EXPIRED)


@dataclass
class ConfigFrame:
    watchdog_timeout_us: int


def encode_command(c: CommandFrame) -> bytes:
    n = len(c.mode)
    payload = CMD_HEAD.pack(c.sequence & 0xFFFFFFFF, n) + b"".join(
        CMD_JOINT.pack(int(c.mode[i]), c.position[i], c.velocity[i], c.effort[i], c.stiffness[i], c.damping[i])
        for i in range(n))
    return frame(TYPE_COMMAND, payload)


def encode_feedback(f: FeedbackFrame) -> bytes:
    n = len(f.position)
    payload = FB_HEAD.pack(f.sequence & 0xFFFFFFFF, f.timestamp_us, f.last_command_us, f.flags, n) + b"".join(
        FB_JOINT.pack(f.position[i], f.velocity[i], f.current[i]) for i in range(n))
    return frame(TYPE_FEEDBACK, payload)


def encode_config(c: ConfigFrame) -> bytes:
    return frame(TYPE_CONFIG, CONFIG.pack(c.watchdog_timeout_us))


def _parse(kind: int, p: bytes) -> CommandFrame | FeedbackFrame | ConfigFrame:
    if kind == TYPE_COMMAND:
        seq, n = CMD_HEAD.unpack_from(p)
        if len(p) != CMD_HEAD.size + n * CMD_JOINT.size:
            raise ValueError("command length does not match its joint count")
        rows = np.array([CMD_JOINT.unpack_from(p, CMD_HEAD.size + i * CMD_JOINT.size) for i in range(n)]).reshape(n, 6)
        return CommandFrame(seq, rows[:, 0].astype(np.uint8), *(rows[:, k].astype(float) for k in range(1, 6)))
    if kind == TYPE_FEEDBACK:
        seq, ts, last_cmd, flags, n = FB_HEAD.unpack_from(p)
        if len(p) != FB_HEAD.size + n * FB_JOINT.size:
            raise ValueError("feedback length does not match its joint count")
        rows = np.frombuffer(p, "<f4", n * 3, FB_HEAD.size).reshape(n, 3).astype(float)
        return FeedbackFrame(seq, ts, flags, rows[:, 0], rows[:, 1], rows[:, 2], last_cmd)
    (timeout,) = CONFIG.unpack(p)
    return ConfigFrame(timeout)


class StreamDecoder:
    """Bytes -> frames of either direction. Never raises; ``stats`` counts every rejection."""

    def __init__(self) -> None:
        self.frames = FrameDecoder(MAX_PAYLOAD, {TYPE_COMMAND, TYPE_FEEDBACK, TYPE_CONFIG})
        self.stats = self.frames.stats
        self.stats.update({"sequence_gaps": 0, "malformed": 0})
        self._last: dict[int, int] = {}

    def feed(self, data: bytes) -> list[CommandFrame | FeedbackFrame | ConfigFrame]:
        out = []
        for kind, payload in self.frames.feed(data):
            try:
                msg = _parse(kind, payload)
            except (ValueError, struct.error):
                self.stats["malformed"] += 1
                continue
            if kind in (TYPE_COMMAND, TYPE_FEEDBACK):
                last = self._last.get(kind)
                if last is not None and msg.sequence != (last + 1) & 0xFFFFFFFF:
                    self.stats["sequence_gaps"] += 1
                self._last[kind] = msg.sequence
            out.append(msg)
        return out
