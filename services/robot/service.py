"""robot node: follow the latest JointTrajectory through the control board at the command rate,
enforcing joint, velocity and effort limits whatever arrives, and publish the measured state.

Commands go out from a thread of their own (real-time priority where the OS allows,
shared/realtime.py) on wall time, each as a plan: the setpoint in force now and those of the next
``lookahead_s`` of the trajectory, which the board plays if the next frame is late. Its 10 ms
watchdog counts from the plan's last knot, so a host paused for less than the look-ahead (a busy
machine, a virtual machine descheduled) leaves the robot on its path instead of braking it, and a
host that stops for good brakes it 10 ms after the path it sent runs out.

The host clamps into soft limits (the URDF limits less a margin) and installs the board's limits
(half that margin) by config frame, where the board brakes a joint that would otherwise coast past
them (services/robot/board_sim.py).

The arm gate: a trajectory moves the robot only while it is armed (``@cmd/arm {"armed": true}``;
``start_armed`` sets the state at start). Disarming, or ``@cmd/hold {"disarm": true}`` (the
dashboard's stop), drops the trajectory, holds where the last command stood and ignores every
trajectory until armed again. Both are answered by this node alone, so they work whatever runs
upstream (policy, trajopt)."""

from __future__ import annotations

import asyncio
import threading
import time
from dataclasses import dataclass

import numpy as np

from services.robot.driver import BoardDriver
from services.robot.safety import (
    WATCHDOG_TIMEOUT_S,
    CommandRejectedError,
    board_limits,
    check_finite,
    limit_step,
    pneumatic_joints,
    soft_limits,
)
from services.robot.tracking import CommandClock, TrajectoryFollower
from shared import msgs
from shared.keys import robot_state_key
from shared.kinematics import load_robot
from shared.protocols.robot_board import Mode
from shared.realtime import lock_memory, raise_priority, raise_process_priority, thread_schedstat
from shared.robots.registry import DEFAULT_ROBOT, describe
from shared.runtime import Node

GAPS_KEPT = 100
# A gap within this of the board's braking point may brake a board that hears commands up to 1 ms
# late (USB; the simulated board's arrival stamps, services/world/arrival_stamper.py).
GAP_MARGIN_S = 0.001
VELOCITY_SLACK = 1.1  # trajectory time runs at most this much faster than wall time (CommandClock)


def command_modes(joint_names: list[str], finger_mode: str = "position") -> np.ndarray:
    """The board mode per joint: POSITION, or PNEUMATIC for joints with a muscle pair when
    ``finger_mode`` is "pneumatic". Raises ValueError for an unknown finger mode or a robot without
    pneumatic joints (the board would brake them: services/robot/safety.py)."""
    modes = np.full(len(joint_names), Mode.POSITION, np.uint8)
    if finger_mode == "position":
        return modes
    if finger_mode != "pneumatic":
        raise ValueError(f"robot: finger_mode must be 'position' or 'pneumatic', got {finger_mode!r}")
    drive = pneumatic_joints(tuple(joint_names))
    if not drive.any():
        raise ValueError("robot: finger_mode = 'pneumatic', but no joint of this robot has a pneumatic drive "
                         "(only the hand-arm's finger joints do)")
    modes[drive] = Mode.PNEUMATIC
    return modes


class RobotService:
    @dataclass
    class Params:
        port: str = ""
        baudrate: int = 3_000_000
        robot: str = DEFAULT_ROBOT
        command_rate_hz: float = 125.0
        # Each frame carries the trajectory's setpoints for this long ahead, knot_spacing_s apart (at
        # most 15 knots); 0: single commands, and the board brakes 10 ms after the host's last one.
        # 112 ms rides out the 50-110 ms pauses a loaded virtual machine gives a real-time thread
        # (bench/soak.py); 8 knots at 125 Hz: 787-byte frames, 98 kB/s of the 3 Mbaud link.
        lookahead_s: float = 0.112
        knot_spacing_s: float = 0.016
        state_rate_hz: float = 100.0
        # "pneumatic": joints with a muscle pair (the hand-arm's fingers) follow the trajectory in the
        # board's PNEUMATIC mode (two-stage pressure PID, thesis 7.3.2) instead of POSITION.
        finger_mode: str = "position"
        # SCHED_FIFO priority of the command thread and of the serial reader (0: normal priority);
        # refused by the OS -> nice -10 or normal priority, logged (shared/realtime.py).
        rt_priority: int = 10
        # SCHED_FIFO priority of the service's other threads (event loop, Zenoh's), which share the
        # command thread's GIL (0: nice -10); only while the command thread is real-time. As high as
        # the command thread's: one holding the GIL must not wait behind the gloves' threads (5) or the
        # kernel's tty workers (9) while the command thread waits for it.
        process_rt_priority: int = 10
        config_period_s: float = 1.0  # the limits config frame is repeated this often (a board may reset)
        start_armed: bool = True  # false: the robot holds until armed (@cmd/arm)

    def __init__(self, node: Node, params: Params) -> None:
        self.node = node
        self.p = params
        model = load_robot(params.robot)
        self.joint_names = model.joint_names
        self.limits = soft_limits(model)  # the host never commands beyond these
        self.board_limits = board_limits(model)  # the board's, between these and the URDF's
        self.modes = command_modes(self.joint_names, params.finger_mode)
        self.follower = TrajectoryFollower(self.joint_names)
        self.command_clock = CommandClock(max_rate=VELOCITY_SLACK)
        self.driver = BoardDriver(params.port, params.baudrate, describe(params.robot).board_order, node.log,
                                  params.rt_priority)
        if node.instance != params.robot:  # trajopt and panel look for xm/robot/<robot model>/state
            node.log.warning("robot instance %r runs model %r: its state goes to %s, not %s", node.instance,
                             params.robot, node.key("state"), robot_state_key(params.robot))
        self.state_pub = node.output("state")
        self.rejections: dict[str, int] = {}
        self.target: np.ndarray | None = None
        self.armed = params.start_armed
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_config = -np.inf
        self.gaps_after: list[int] = []  # the last command's sequence before each recent gap near the watchdog's
        self.gap_parts: list[dict] = []  # where the time of each of those gaps went (_count_gap)
        self.knots = int(round(params.lookahead_s / params.knot_spacing_s)) if params.lookahead_s > 0 else 0
        if not 0 <= self.knots < 16 or (self.knots and params.knot_spacing_s * 1e6 > 0xFFFF):
            raise ValueError(f"robot: lookahead_s {params.lookahead_s} at knot_spacing_s {params.knot_spacing_s} "
                             "needs 0 to 15 knots at most 65 ms apart")
        # A gap between two frames longer than this brakes the board (the plan ran out 10 ms before).
        self.brake_gap_s = WATCHDOG_TIMEOUT_S + self.knots * params.knot_spacing_s
        self.stream = {"priority": "not started", "ticks": 0, "late_ticks": 0, "max_gap_ms": 0.0,
                       "gaps_over_watchdog": 0, "gaps_bridged": 0, "configs": 0, "memory_locked": False,
                       "errors": 0, "brake_gap_ms": round(self.brake_gap_s * 1e3, 1)}
        node.input("trajectory", self.on_trajectory)
        node.queryable("hold", self.cmd_hold)
        node.queryable("arm", self.cmd_arm)
        node.clock.on_jump(lambda _old, _new: self.cmd_hold({}))  # a trajectory of the old timeline: hold
        node.health_extra = lambda: {"armed": self.armed, "link": self.driver.link.stats(),
                                     "decoder": dict(self.driver.decoder.stats),
                                     "rejections": self.rejections, "watchdog": self.driver.watchdog_state,
                                     "command_stream": {**self.stream, "gaps_after": self.gaps_after,
                                                        "gap_parts": self.gap_parts},
                                     "command_clock_jumps": self.command_clock.jumps}

    def _reject(self, reason: str) -> None:
        self.rejections[reason] = self.rejections.get(reason, 0) + 1
        self.node.stats.count("command_rejected")
        self.node.logs.warning(f"rejected:{reason}", "trajectory rejected", reason=reason)

    def on_trajectory(self, msg) -> None:
        if not self.armed:
            self.node.stats.count("ignored_disarmed")
            return
        reason = self.follower.load(msg, self.node.clock.now())
        if reason:
            self._reject(reason)

    def cmd_hold(self, req: dict) -> dict:
        """Drop the trajectory and hold; ``{"disarm": true}`` also disarms (the dashboard's stop)."""
        if req.get("disarm"):
            self.armed = False
        self.follower = TrajectoryFollower(self.joint_names)
        return {"ok": True, "armed": self.armed}

    def cmd_arm(self, req: dict) -> dict:
        """``{"armed": bool}`` arms or disarms (disarm holds); ``{}`` only reports the state."""
        armed = req.get("armed")
        if armed is not None:
            if not isinstance(armed, bool):
                raise ValueError(f"armed must be true or false, got {armed!r}")
            if not armed:
                return self.cmd_hold({"disarm": True})
            self.armed = True
        return {"ok": True, "armed": self.armed}

    async def run(self) -> None:
        self.node.spawn(self.driver.run(), name="serial")
        self.node.spawn(self._publish_state(), name="state")
        self._thread = threading.Thread(target=self._command_loop, name="robot-commands", daemon=True)
        self._thread.start()
        while self._thread.is_alive():  # the thread ends only at close()
            await asyncio.sleep(0.5)
        if not self._stop.is_set():
            raise RuntimeError("the command thread ended")

    def _command_loop(self) -> None:
        """Commands on wall time, one per period: the board's watchdog must be fed even if the sim
        clock stalls or the event loop is busy. A late wake-up sends one command, never a burst."""
        self.stream["priority"] = raise_priority("robot command stream", self.node.log, self.p.rt_priority)
        # The GIL ties this thread to every other of the process: one holding it must not wait for a CPU
        # behind other processes (at nice -10 it still did, and the board braked after a 10 ms gap).
        if self.p.rt_priority > 0:
            raise_process_priority("robot", self.node.log, rt_priority=self.p.process_rt_priority)
            self.stream["memory_locked"] = lock_memory("robot", self.node.log)
        period = 1.0 / self.p.command_rate_hz
        next_t = last = time.monotonic()
        last_sent: float | None = None
        run_delay, slices = thread_schedstat()
        while not self._stop.is_set():
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            now = time.monotonic()
            woke_late = now - next_t
            if woke_late > period:
                self.stream["late_ticks"] += 1
                next_t = now
            elapsed, last = now - last, now
            self.stream["ticks"] += 1
            self.stream["max_gap_ms"] = max(self.stream["max_gap_ms"], elapsed * 1e3)
            sequence = self.driver.sequence
            try:
                self._command_tick(elapsed, now)
            except Exception as exc:  # a bug in one tick must not stop the stream (the board would brake)
                self.stream["errors"] += 1
                self.node.log.exception("command tick failed: %r", exc)
            if self.driver.sequence != sequence:  # sent: the gap the board sees is between the writes
                sent = time.monotonic()
                delay_now, slices_now = thread_schedstat()
                if last_sent is not None:
                    self._count_gap(sent - last_sent, sequence - 1, {
                        "woke_late_ms": round(woke_late * 1e3, 2), "tick_ms": round((sent - now) * 1e3, 2),
                        "waited_for_cpu_ms": round((delay_now - run_delay) * 1e3, 2),
                        "times_on_cpu": slices_now - slices})
                run_delay, slices = delay_now, slices_now
                last_sent = sent
            else:
                last_sent = None  # no feedback, no commands: the board brakes, as it should

    def _count_gap(self, gap: float, before: int, parts: dict | None = None) -> None:
        """A gap between two frames written: one that brakes the board is counted (one over the
        watchdog timeout that a plan bridged, separately), near it the sequence of the frame before
        it is kept (bench/robot.py tells the board's brakes apart), with where the time went
        (``parts``: the wake-up's lateness, the tick's own time, which holds the GIL wait and the
        write, and the time the thread waited for a CPU since the last write)."""
        self.stream["gaps_over_watchdog"] += gap > self.brake_gap_s
        self.stream["gaps_bridged"] += WATCHDOG_TIMEOUT_S < gap <= self.brake_gap_s
        if gap > self.brake_gap_s - GAP_MARGIN_S:
            self.gaps_after = (self.gaps_after + [before])[-GAPS_KEPT:]
            self.gap_parts = (self.gap_parts + [{"after": before, "gap_ms": round(gap * 1e3, 2),
                                                 "at_unix": round(time.time(), 3), **(parts or {})}])[-GAPS_KEPT:]

    def _command_tick(self, elapsed: float, now: float | None = None) -> None:
        """One command, ``elapsed`` wall seconds after the previous one."""
        fb = self.driver.feedback
        if fb is None or not self.driver.link.connected:
            self.target = None  # no state, no commands: the board's watchdog keeps the robot braked
            self._last_config = -np.inf
            return
        now = time.monotonic() if now is None else now
        if now - self._last_config >= self.p.config_period_s and self.driver.configure(self.board_limits):
            self._last_config = now
            self.stream["configs"] += 1
        if self.target is None:  # start by holding where the robot is (inside the soft limits)
            self.target = np.clip(fb.position, self.limits.lower, self.limits.upper)
        t, advanced = self.command_clock.advance(self.node.clock.now(), elapsed)
        sample = self.follower.sample(t) if self.armed else None  # disarmed: hold, whatever the follower holds
        goal, velocity = sample if sample is not None else (self.target, np.zeros(len(self.target)))
        try:
            check_finite(goal, "trajectory sample")
        except CommandRejectedError as exc:
            self._reject(str(exc))
            goal, velocity = self.target, np.zeros(len(self.target))
        # The rate limit allows what the axes can move in the time since the last command: the wall
        # time, or the trajectory time when it catches up (at most VELOCITY_SLACK x the wall time), so a
        # trajectory within the velocity limit is never clamped because the time between two commands
        # jittered, nor a re-plan's small step while trajectory time waits for a late clock.
        self.target, reasons = limit_step(goal, self.target, self.limits, max(advanced, elapsed))
        for r in reasons:
            self.node.stats.count(f"clamped_{r}")
        velocity = np.clip(velocity, -self.limits.velocity, self.limits.velocity)
        effort = np.zeros(len(self.target))
        if not self.knots:
            self.driver.send(self.modes, self.target, velocity, effort)
            return
        positions, velocities = self._plan(t, velocity)
        self.driver.send_plan(self.modes, positions, velocities, effort, self.p.knot_spacing_s)

    def _plan(self, t: float, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The command in force now and the trajectory's next knots, each within the limits of the
        one before it (disarmed, or no trajectory: holding the target)."""
        dt = self.p.knot_spacing_s
        positions, velocities = [self.target], [velocity]
        for i in range(1, self.knots + 1):
            sample = self.follower.sample(t + i * dt) if self.armed else None
            goal, v = sample if sample is not None else (positions[-1], np.zeros(len(self.target)))
            if not (np.isfinite(goal).all() and np.isfinite(v).all()):  # tick 0 has counted it
                goal, v = positions[-1], np.zeros(len(self.target))
            positions.append(limit_step(goal, positions[-1], self.limits, dt)[0])
            velocities.append(np.clip(v, -self.limits.velocity, self.limits.velocity))
        return np.array(positions), np.array(velocities)

    async def _publish_state(self) -> None:
        async for t in self.node.clock.ticks(self.p.state_rate_hz):
            fb = self.driver.feedback
            if fb is None:
                self.node.set_status("degraded", "no feedback from the control board")
                continue
            self.node.set_status("ok" if not fb.watchdog_expired else "degraded",
                                 "" if not fb.watchdog_expired else "board watchdog braking")
            self.state_pub.put(msgs.make(
                "sensor_msgs/msg/JointState", header=msgs.header(t, "world"), name=list(self.joint_names),
                position=fb.position.astype(float), velocity=fb.velocity.astype(float),
                effort=fb.current.astype(float)))

    async def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, 1.0)
        self.driver.close()
