"""The simulated devices the world hosts on ptys, speaking the real byte protocols.

GloveDevice: the glove readout module (thesis 4.8.3): contact forces -> sensor model ->
complex impedance frame -> the tactile wire protocol, at the readout rate.
BoardDevice: the robot control board (thesis 6.2): command frames in, feedback frames out,
motor efforts to MuJoCo, watchdog braking on host silence.
"""

from __future__ import annotations

import collections
import logging
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from services.glove.sensor_model import GloveSensorModel
from services.robot.board_sim import BoardSim
from services.robot.safety import Limits
from services.world.arrival_stamper import HEADER
from services.world.pty_device import PtyDevice
from shared.protocols import robot_board, tactile

log = logging.getLogger("xm")

STAMPER = Path(__file__).with_name("arrival_stamper.py")

GRAVITY = np.array([0.0, 0.0, -9.81])


def hand_frame(keypoints: np.ndarray) -> np.ndarray:
    """Rotation (columns x, y, z in world) of the back of a hand from its wrist, index and little
    finger bases (keypoints 0, 5, 17): x toward the fingers, z out of the palm plane."""
    wrist, index, little = keypoints[0], keypoints[5], keypoints[17]
    x = (index + little) / 2 - wrist
    x = x / max(np.linalg.norm(x), 1e-9)
    z = np.cross(x, index - little)
    z = z / max(np.linalg.norm(z), 1e-9)
    return np.column_stack([x, np.cross(z, x), z])


class ImuModel:
    """SIMULATED wrist IMU: specific force and angular rate in the hand frame from the teacher's
    keypoints, by finite differences over about ``BASELINE_S`` whatever the readout rate (like the
    sensor's digital low-pass filter: shorter differences would turn keypoint jitter into spikes).
    No noise: the protocol's LSBs quantize."""

    BASELINE_S = 0.02

    def __init__(self) -> None:
        self.history: list[tuple[float, np.ndarray, np.ndarray]] = []  # (t, wrist, R), oldest first

    def _near(self, t: float) -> tuple[float, np.ndarray, np.ndarray]:
        return min(self.history, key=lambda h: abs(h[0] - t))

    def sample(self, t: float, keypoints: np.ndarray) -> np.ndarray:
        R = hand_frame(keypoints)
        self.history = [h for h in self.history if h[0] >= t - 3 * self.BASELINE_S] + [
            (t, keypoints[0].astype(float), R)]
        accel, gyro = -GRAVITY, np.zeros(3)
        t2, p2, R2 = self.history[-1]
        t1, p1, R1 = self._near(t2 - self.BASELINE_S)
        t0, p0, _ = self._near(t1 - self.BASELINE_S)
        if t2 > t1 > t0:
            v1, v2 = (p1 - p0) / (t1 - t0), (p2 - p1) / (t2 - t1)
            accel = 2 * (v2 - v1) / (t2 - t0) - GRAVITY
            dR = R1.T @ R2  # body-frame increment; its skew part / dt is the rate
            gyro = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / (2 * (t2 - t1))
        return np.concatenate([R.T @ accel, gyro]).astype(np.float32)


class GloveDevice:
    """SIMULATED glove readout module: registers over the same wire as the FPGA core (replies to
    host reads and writes with tactile.RegisterFile semantics), frames only while control.run is
    set, only the enabled lines, and a wrist IMU sample per frame while imu_enable is set.

    The frame period is the core's, window x tick_div / f_clk. The module starts with the tick_div
    that gives ``rate_hz`` at the default window (the deployment's rate: 2 cores cannot simulate
    1 kHz x 2 gloves), and a host that writes window or tick_div changes the rate as on the FPGA."""

    def __init__(self, port: str, hand: str, seed: int = 0, rate_hz: float = 100.0) -> None:
        self.hand = hand
        self.pty = PtyDevice(port)
        self.model = GloveSensorModel(seed)
        self.registers = tactile.RegisterFile()
        regs = self.registers.values
        regs[tactile.REG_TICK_DIV] = int(np.clip(round(tactile.CORE_CLOCK_HZ / (rate_hz * regs[tactile.REG_WINDOW])),
                                                 1, 0xFFFF))
        self._next_frame = 0.0
        self.commands = tactile.CommandDecoder()
        self.imu = ImuModel()
        self.sequence = 0
        self.replies = 0
        self._config_changed = False

    def poll(self) -> None:
        """Answers pending register commands (the world calls this every tick)."""
        data = self.pty.read()
        if not data:
            return
        for cmd in self.commands.feed(data):
            reply = self.registers.handle(cmd)
            if cmd.value is not None and reply.status == tactile.REPLY_OK:
                self._config_changed = True
            self.pty.write(tactile.encode_reply(reply.address, reply.value, reply.status))
            self.replies += 1

    @property
    def period_s(self) -> float:
        """Seconds per frame from the window and tick_div registers (zero values count as 1)."""
        regs = self.registers.values
        return max(regs[tactile.REG_WINDOW], 1) * max(regs[tactile.REG_TICK_DIV], 1) / tactile.CORE_CLOCK_HZ

    def restart_schedule(self) -> None:
        """The simulated time restarted: the next readout window ends at once."""
        self._next_frame = 0.0

    def due(self, t: float) -> bool:
        """True when a readout window ends at ``t`` (then the next one is scheduled)."""
        if t < self._next_frame:
            return False
        self._next_frame = t + self.period_s - 1e-9
        return True

    def emit(self, t: float, region_forces: np.ndarray, hand_keypoints: np.ndarray | None = None) -> None:
        """One readout window ending at ``t``: a frame, if the module is running."""
        self.poll()
        regs = self.registers.values
        imu = self.imu.sample(t, hand_keypoints) if hand_keypoints is not None else None
        if not regs[tactile.REG_CONTROL] & 1:
            return
        tx, rx = regs[tactile.REG_TX_ENABLE], regs[tactile.REG_RX_ENABLE]
        impedance = self.model.impedance(np.asarray(region_forces, float), t)
        status = tactile.STATUS_CONFIG_CHANGED if self._config_changed else 0
        self._config_changed = False
        frame = tactile.TactileFrame(sequence=self.sequence & 0xFFFFFFFF, timestamp_us=int(t * 1e6),
                                     impedance=impedance,
                                     imu=imu[None] if imu is not None and regs[tactile.REG_IMU_ENABLE] else None,
                                     tx_mask=tx, rx_mask=rx, status=status)
        self.pty.write(tactile.encode_frame(frame))
        self.sequence += 1
        regs[tactile.REG_FRAME_COUNT] = frame.sequence

    def stats(self) -> dict:
        return {"frames": self.sequence, "register_replies": self.replies, "dropped_bytes": self.pty.dropped_bytes,
                **{f"rx_{k}": v for k, v in self.commands.stats.items()}}

    def close(self) -> None:
        self.pty.close()


class HoldLog:
    """Pure: the episodes in which the world held its clock for the robot's wire (consecutive steps
    ``BoardDevice.step`` refused), so a pause of the whole cell can be traced to the pty. A hold of
    ``LONG_S`` or more is logged with how old the stamper's horizon was when it began."""

    LONG_S = 0.1

    def __init__(self) -> None:
        self.count = self.long = 0
        self.longest_s = 0.0
        self.last_long: dict | None = None
        self._began: tuple[float, float | None] | None = None  # (wall, horizon) at the first refused step

    def waiting(self, now: float, horizon: float | None) -> None:
        if self._began is None:
            self._began = (now, horizon)

    def stepped(self, now: float, horizon: float | None) -> None:
        if self._began is None:
            return
        (began, horizon0), self._began = self._began, None
        held = now - began
        self.count += 1
        self.longest_s = max(self.longest_s, held)
        if held >= self.LONG_S:
            self.long += 1
            self.last_long = {"held_s": round(held, 4), "at": round(began, 3),
                              "horizon_age_s": None if horizon0 is None else round(began - horizon0, 4),
                              "horizon_moved_s": None if horizon is None or horizon0 is None
                              else round(horizon - horizon0, 4)}
            log.warning("world held for the robot's wire", extra={"fields": self.last_long})

    def stats(self) -> dict:
        return {"count": self.count, f"over_{int(self.LONG_S * 1000)}ms": self.long,
                "longest_s": round(self.longest_s, 4), "last_long": self.last_long}


class BoardDevice:
    """SIMULATED control board on a pty.

    The world simulates in bursts of a few physics steps, then sleeps (or, when it runs late, steps
    flat out to catch up), so the host's commands, which come on wall time, would all reach the board
    at the first step of a burst: the gaps between them in simulated time would differ from the
    real ones and the 10 ms watchdog would brake although the host never paused. So a helper
    process (services/world/arrival_stamper.py) stamps each read from the host with when the host
    wrote it (at most one probe period late; frames of a backlog the stamper read late are placed by
    ``_release_batch``), and ``step`` hands each command to the board at the step whose simulated
    time matches (``sim_time_of``, the world's wall -> simulated time map), kicking the watchdog at
    the previous kick plus the host's own spacing (``_kick_time``).

    The pty's own transfer can hold the host's bytes back far longer than 10 ms on a busy host (the
    stamper says why); a real board's UART sees them within about a millisecond. So once a command
    is overdue on what has arrived, the board's clock does not run past the stamper's horizon (the
    time up to which everything the host wrote has arrived): ``step`` returns False and the world
    waits, then steps on. The board brakes within 10 ms plus one physics step of the host's last
    command in board time, and never because the simulated wire was slow. A horizon older than
    ``MAX_HOLD_S`` (a stalled pty, a dead stamper) holds nothing back."""

    MAX_HOLD_S = 1.0  # a command never waits longer than this in wall time, whatever the map says

    def __init__(self, port: str, joint_names: list[str], limits: Limits | None = None) -> None:
        self.pty = PtyDevice(port)
        self.decoder = robot_board.StreamDecoder()
        self.board = BoardSim(joint_names, limits)
        self.feedback_frames = 0
        self._inbox: collections.deque[tuple[float, object]] = collections.deque()
        self._stamped = bytearray()
        self.horizon: float | None = None  # wall time up to which every byte the host wrote has arrived
        self._kick: tuple[float, float] | None = None  # the last command's (board time, wall stamp)
        self.waits = 0  # steps held back for the wire
        self.holds = HoldLog()
        self._last_stamp = float("-inf")  # stamp of the latest bytes from the host
        self._batch: list = []  # frames since the last horizon, and when the last of them was read
        self._batch_upper = float("-inf")
        fds = [self.pty.master, self.pty.slave]
        self._stamper = subprocess.Popen([sys.executable, str(STAMPER), *map(str, fds)],
                                         pass_fds=fds, stdout=subprocess.PIPE,
                                         stdin=subprocess.DEVNULL, start_new_session=True)
        os.set_blocking(self._stamper.stdout.fileno(), False)

    def restart_schedule(self) -> None:
        """The simulated time restarted."""
        self.board.restart_clock()
        self._kick = None

    def _drain_stamper(self) -> None:
        """Commands the stamper read, with their arrival times, into the inbox."""
        try:
            while chunk := os.read(self._stamper.stdout.fileno(), 1 << 16):
                self._stamped += chunk
        except BlockingIOError:
            pass
        buf, at = self._stamped, 0
        while len(buf) - at >= HEADER.size:
            t, n = HEADER.unpack_from(buf, at)
            if len(buf) - at - HEADER.size < n:
                break
            if n:
                self.arrived(bytes(buf[at + HEADER.size:at + HEADER.size + n]), t)
            else:
                self.heard_until(t)
            at += HEADER.size + n
        del buf[:at]

    def arrived(self, data: bytes, t_wall: float) -> None:
        """Bytes from the host, written after the horizon and by ``t_wall`` (monotonic seconds). Their
        frames wait for the next horizon (``heard_until``), which closes what is known of when they
        were written (``_release_batch``)."""
        self._batch += self.decoder.feed(data)
        self._batch_upper = t_wall

    def heard_until(self, t_wall: float) -> None:
        """Every byte the host wrote before ``t_wall`` (monotonic seconds) has arrived."""
        self._release_batch(t_wall)
        self.horizon = t_wall if self.horizon is None else max(self.horizon, t_wall)

    def _release_batch(self, closing: float | None = None) -> None:
        """The frames read since the last horizon, into the inbox with their write times. Each was
        written after the previous frame and the last horizon, and by its read's stamp; where that
        leaves room (the stamper itself could not run for a while, and read a backlog) they are placed
        evenly between the previous frame and the closing horizon, inside those bounds: the kindest
        reading of the evidence, so a gap the host may not have left shows nowhere, while one the
        probes prove (no frame between two horizons more than 10 ms apart) still does."""
        batch, upper = self._batch, self._batch_upper
        if not batch:
            return
        lower = max(self._last_stamp, self.horizon if self.horizon is not None else float("-inf"))
        if not np.isfinite(lower) or lower >= upper:
            stamps = [upper] * len(batch)
        else:
            prev = self._last_stamp if np.isfinite(self._last_stamp) else lower
            end = max(upper, closing if closing is not None else upper)
            stamps = [min(max(prev + (end - prev) * (i + 1) / (len(batch) + 1), lower), upper)
                      for i in range(len(batch))]
        for stamp, msg in zip(stamps, batch, strict=True):
            self._inbox.append((stamp, msg))
        self._last_stamp = stamps[-1]
        self._batch = []

    def step(self, sim, sim_time_of: Callable[[float], float] | None = None, now: float | None = None) -> bool:
        """One physics step: commands due by now to the board, the board's efforts to MuJoCo, its
        feedback to the pty. Without ``sim_time_of`` every command that arrived is due at once.
        Returns False, without stepping, while the wire may still hold a command that decides
        whether the watchdog expires at this step (the caller waits and calls again)."""
        self._drain_stamper()
        inbox, now = self._inbox, time.monotonic() if now is None else now
        if self._batch and now - self._batch_upper >= self.MAX_HOLD_S:  # no horizon comes (a dead stamper)
            self._release_batch()
        while inbox:
            t_arrival, msg = inbox[0]
            at = sim.time
            if sim_time_of is not None:
                if sim_time_of(t_arrival) > sim.time and now - t_arrival < self.MAX_HOLD_S:
                    break
                at = self._kick_time(t_arrival, sim_time_of, sim.time)
            inbox.popleft()
            self.board.receive(msg, at)
        if sim_time_of is not None and self._undecided(sim.time, sim_time_of, now):
            self.waits += 1
            self.holds.waiting(now, self.horizon)
            return False
        self.holds.stepped(now, self.horizon)
        self.pty.flush()
        q, qd = sim.joint_state()
        efforts, feedback = self.board.step(sim.time, q, qd, sim.physics_dt)
        sim.set_efforts(efforts)
        if feedback is not None:
            self.pty.write(robot_board.encode_feedback(feedback))
            self.feedback_frames += 1
        return True

    def _kick_time(self, stamp: float, sim_time_of: Callable[[float], float], now_sim: float) -> float:
        """The board time a command stamped ``stamp`` kicks the watchdog: the previous kick plus the
        host's own spacing since the previous command, so that a world re-pacing its map (it fell
        far behind) moves no command onto another's time; never before the previous kick or 0,
        never after the current step (a command the world could not yet hand over)."""
        if self._kick is None:
            at = sim_time_of(stamp)
        else:
            at = self._kick[0] + sim_time_of(stamp) - sim_time_of(self._kick[1])
        at = min(max(at, self._kick[0] if self._kick else 0.0, 0.0), now_sim)
        self._kick = (at, stamp)
        return at

    def _undecided(self, t: float, sim_time_of: Callable[[float], float], now: float) -> bool:
        """The watchdog would expire at ``t`` on the commands that arrived, but the host may have
        written one before ``t`` that the pty has not delivered yet."""
        dog = self.board.watchdog
        if dog.state != "ok" or not dog.expired(t) or self.horizon is None or now - self.horizon >= self.MAX_HOLD_S:
            return False
        return sim_time_of(self.horizon) < t

    def stats(self) -> dict:
        cmd = self.board.command
        modes = {} if cmd is None else {m.name.lower(): int((cmd.mode == m).sum()) for m in robot_board.Mode
                                        if (cmd.mode == m).any()}
        return {"feedback_frames": self.feedback_frames, "dropped_bytes": self.pty.dropped_bytes,
                "command_modes": modes, "plans": self.board.counters["plans"],
                "watchdog_brakes": self.board.counters["brake_events"],
                "limit_brakes": self.board.counters["limit_brakes"], "last_brake": self.board.last_brake,
                "brakes_after": self.board.brakes_after,
                "waits_for_wire": self.waits, "wire_holds": self.holds.stats(),
                "wire_lag_s": None if self.horizon is None else round(time.monotonic() - self.horizon, 4),
                "muscle_pressure_max_bar": float(self.board.pressure.max()),
                **{f"rx_{k}": v for k, v in self.decoder.stats.items()}}

    def close(self) -> None:
        self._stamper.kill()
        self._stamper.wait(2)
        self._stamper.stdout.close()
        self.pty.close()
