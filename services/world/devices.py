"""The simulated devices the world hosts on ptys, speaking the real byte protocols.

GloveDevice: the glove readout module (thesis 4.8.3): contact forces -> sensor model ->
complex impedance frame -> the tactile wire protocol, at the readout rate.
BoardDevice: the robot control board (thesis 6.2): command frames in, feedback frames out,
motor efforts to MuJoCo, watchdog braking on host silence.
"""

from __future__ import annotations

import numpy as np

from services.glove.sensor_model import GloveSensorModel
from services.robot.board_sim import BoardSim
from services.world.pty_device import PtyDevice
from shared.protocols import robot_board, tactile


class GloveDevice:
    def __init__(self, port: str, hand: str, seed: int = 0) -> None:
        self.hand = hand
        self.pty = PtyDevice(port)
        self.model = GloveSensorModel(seed)
        self.sequence = 0

    def emit(self, t: float, region_forces: np.ndarray) -> None:
        impedance = self.model.impedance(np.asarray(region_forces, float), t)
        frame = tactile.TactileFrame(sequence=self.sequence & 0xFFFFFFFF, timestamp_us=int(t * 1e6),
                                     impedance=impedance, imu=None)
        self.pty.write(tactile.encode_frame(frame))
        self.sequence += 1

    def stats(self) -> dict:
        return {"frames": self.sequence, "dropped_bytes": self.pty.dropped_bytes}

    def close(self) -> None:
        self.pty.close()


class BoardDevice:
    def __init__(self, port: str, joint_names: list[str]) -> None:
        self.pty = PtyDevice(port)
        self.decoder = robot_board.StreamDecoder()
        self.board = BoardSim(joint_names)
        self.feedback_frames = 0

    def step(self, sim) -> None:
        data = self.pty.read()
        if data:
            for msg in self.decoder.feed(data):
                self.board.receive(msg, sim.time)
        q, qd = sim.joint_state()
        efforts, feedback = self.board.step(sim.time, q, qd, sim.physics_dt)
        sim.set_efforts(efforts)
        if feedback is not None:
            self.pty.write(robot_board.encode_feedback(feedback))
            self.feedback_frames += 1

    def stats(self) -> dict:
        return {"feedback_frames": self.feedback_frames, "dropped_bytes": self.pty.dropped_bytes,
                **{f"rx_{k}": v for k, v in self.decoder.stats.items()}}

    def close(self) -> None:
        self.pty.close()
