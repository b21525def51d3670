"""SIMULATED robot control board (thesis 6.2): per-joint control modes, motor currents, limits and
the 10 ms watchdog. Pure logic, no I/O: the world decodes bytes from the pty, hands the messages to
``receive`` and calls ``step`` every physics step with the joint state; ``step`` returns the joint
efforts for MuJoCo and, at the feedback rate, a FeedbackFrame to encode onto the pty.

On the real board the same behaviour lives in the FPGA (hdl/motor/: encoder readout, PID,
commutation, PWM, watchdog). A plan frame is a command plus the setpoints of the next tens of
milliseconds: the board moves through them (linear interpolation, the last one held) and its
watchdog counts from the plan's last knot, so a host that is a few tens of milliseconds late keeps
the robot on its planned path instead of braking it. When no command arrived for the watchdog
timeout (after a plan: for the timeout after its last knot) the board brakes:
damping only (shorted windings), so the Z axes, which carry the arm's weight, sink slowly (about
5 mm/s here) instead of dropping, as on the real robot (thesis 6.3). With position limits installed
(power-up limits, or the host's config frame) setpoints are clamped into them and a joint whose
braked stopping distance would carry it past them is braked (``limit_brakes``), so it stops before
the hard stop whatever it was commanded.

Joints with a muscle pair (the hand-arm's fingers, services/robot/pneumatic.py) also run the
PNEUMATIC mode: the two-stage PID of thesis 7.3.2 sets the valves, the muscle pressures integrate
here, and the joint effort is torque_per_bar x (flexor - extensor pressure). Outside that mode, and
whenever the board brakes, both muscles vent; the brake itself is the same damper as for every axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.robot.pneumatic import (
    PneumaticParams,
    TwoStageController,
    has_pneumatic_drive,
    muscle_pressures,
    pneumatic_params,
)
from services.robot.safety import (
    WATCHDOG_TIMEOUT_S,
    CommandRejectedError,
    Limits,
    LimitsError,
    SafetyState,
    Watchdog,
    enforce_with_flags,
)
from shared.protocols.robot_board import (
    CLAMPED,
    COMMAND_REJECTED,
    CONFIG_REJECTED,
    JOINT_BRAKING,
    JOINT_POSITION_LIMIT,
    LIMITS_ACTIVE,
    NO_COMMAND_YET,
    WATCHDOG_EXPIRED,
    CommandFrame,
    ConfigFrame,
    FeedbackFrame,
    Mode,
    PlanFrame,
)
from shared.robots.registry import joints_with

DEFAULT_DT = 0.001
BRAKES_KEPT = 100
BRAKE, POSITION, VELOCITY, EFFORT, IMPEDANCE, PNEUMATIC = (int(m) for m in Mode)  # ints: fast array compares


ARM_JOINTS = joints_with("harmonic_joints")  # the hand-arm's arm joints (shared/robots/hand_arm.py)


def encoder_lsb(name: str) -> float:
    """Resolution of the 15-bit absolute encoder on the motor shaft, at the joint (thesis 6.2):
    linear axes 40 mm of belt per motor turn (Z axes geared 2:1), wrist and gripper 5:1; the
    hand-arm's arm joints behind 101:1 harmonic drives, its finger joints 5:1."""
    if name in ARM_JOINTS:
        return 2 * np.pi / 101 / 2 ** 15
    if name.endswith("_z"):
        return 0.020 / 2 ** 15
    if name.endswith(("_x", "_y")):
        return 0.040 / 2 ** 15
    if "finger" in name:
        return 0.020 / 2 ** 15
    return 2 * np.pi / 5 / 2 ** 15


@dataclass(frozen=True)
class AxisParams:
    kp: float  # position loop, N/m or N m/rad
    kd: float
    ki: float
    i_clamp: float  # N or N m: the narrowly clamped integral term (thesis 6.3)
    kv: float  # velocity loop
    brake_damping: float  # N s/m or N m s/rad with the windings shorted
    kt: float  # joint effort per motor ampere (torque constant times transmission)
    effort_max: float  # what the motor and driver can give
    inertia: float  # effective moving mass (kg) or inertia (kg m^2) at the joint, for the brake model


def axis_params(name: str) -> AxisParams:
    if name in ARM_JOINTS:
        # Hand-arm: inertias include the drives' reflected inertia (services/world/model.py); the
        # integral carries the arm's weight (up to ~90 N m at the shoulder with the arm stretched out).
        if name.startswith(("shoulder", "elbow")):
            return AxisParams(3000.0, 100.0, 10000.0, 150.0, 300.0, 2000.0, 10.0, 330.0 if name != "elbow" else 150.0,
                              2.0)
        return AxisParams(500.0, 20.0, 2000.0, 20.0, 50.0, 300.0, 2.0, 56.0 if name != "wrist_3" else 28.0, 0.3)
    if has_pneumatic_drive(name):
        return AxisParams(5.0, 0.1, 20.0, 0.2, 0.5, 0.5, 0.05, 2.0, 0.002)
    if "finger" in name:  # the workcell gripper's fingers: light, geared 5:1
        return AxisParams(300.0, 6.0, 0.0, 0.0, 30.0, 20.0, 0.5, 40.0, 0.05)
    if name.endswith("wrist"):
        return AxisParams(30.0, 1.0, 5.0, 0.5, 5.0, 2.0, 0.08, 5.0, 0.01)
    if name.endswith("_z"):
        # Brake: ~10 N of arm weight against 2000 N s/m (+2 of joint friction) sinks at ~5 mm/s.
        return AxisParams(3000.0, 200.0, 8000.0, 40.0, 1000.0, 2000.0, 4.0, 200.0, 1.0)
    return AxisParams(2000.0, 150.0, 1000.0, 20.0, 750.0, 1500.0, 4.0, 200.0, 2.5)


class BoardSim:
    """SIMULATED control board. ``step(t, q, qd) -> (ctrl_effort, feedback | None)``.

    ``limits`` are the board's power-up limits (a config frame can replace them); None means only the
    motors' own effort maxima apply until the host sends a config with limits.
    """

    def __init__(self, joint_names: list[str], limits: Limits | None = None, feedback_period_s: float = 0.004,
                 seed: int = 0, current_noise_a: float = 0.01) -> None:
        self.joint_names = list(joint_names)
        n = len(self.joint_names)
        self.params = [axis_params(j) for j in self.joint_names]
        for f in AxisParams.__dataclass_fields__:
            setattr(self, f, np.array([getattr(p, f) for p in self.params]))
        self.motor_limits = Limits(np.full(n, -1e9), np.full(n, 1e9), np.full(n, 1e9), self.effort_max,
                                   tuple(self.joint_names))
        self.limits = limits if limits is not None else self.motor_limits
        self.limits_active = limits is not None
        self.watchdog = Watchdog(WATCHDOG_TIMEOUT_S)
        self.command: CommandFrame | None = None  # the last accepted frame, as received
        self.plan: PlanFrame | None = None  # the last accepted frame when it was a plan
        self.plan_end: float | None = None  # board time of that plan's last knot
        self.last_safe: np.ndarray | None = None
        self.integral = np.zeros(n)
        self.feedback_period_s = feedback_period_s
        self.current_noise_a = current_noise_a
        self._next_feedback = 0.0
        self._last_t: float | None = None
        self._prev_mode = np.zeros(n, np.uint8)
        self.sequence = 0
        self.config_sequence = 0
        self.last_command_t: float | None = None
        self.last_command_sequence = 0
        self.rng = np.random.default_rng(seed)
        self.lsb = np.array([encoder_lsb(j) for j in self.joint_names])
        self.sticky_flags = 0
        self.f_ext = np.zeros(n)  # observed external joint load (gravity, contacts), N or N m
        self._qd_prev: np.ndarray | None = None
        self._u_prev = np.zeros(n)
        self.counters = {"commands": 0, "plans": 0, "commands_rejected": 0, "configs": 0, "configs_rejected": 0,
                         "brake_events": 0, "clamp_events": 0, "limit_brakes": 0}
        self.last_reasons: list[str] = []
        self.last_brake: dict | None = None  # board times of the latest watchdog brake and the command before it
        self.brakes_after: list[int] = []  # sequence of the last command before each recent watchdog brake
        self._braking = True
        self._in_zone = np.zeros(n, bool)
        # Muscle pairs (PNEUMATIC mode): parameters per joint from pneumatic_params; joints without a
        # drive get a zero torque scale (safety never lets them into the mode anyway).
        muscles = [pneumatic_params(j) or PneumaticParams(torque_per_bar=0.0) for j in self.joint_names]
        col = {f: np.array([getattr(m, f) for m in muscles]) for f in PneumaticParams.__dataclass_fields__}
        self.torque_per_bar, self.fill_rate, self.leak = col["torque_per_bar"], col["fill_rate"], col["leak"]
        self.pneumatic = TwoStageController(col["stiffness"], col["ki"], col["i_clamp"], col["kd"],
                                            col["kp_pressure"], col["ki_pressure"], np.zeros(n), np.zeros((2, n)))
        self.pressure = np.zeros((2, n))  # bar, flexor and extensor per joint; vented at power-up

    @property
    def brake_events(self) -> int:
        return self.counters["brake_events"]

    def measure(self, q: np.ndarray) -> np.ndarray:
        """What the encoders report: quantized, with one LSB of noise."""
        counts = np.round(q / self.lsb) + self.rng.integers(-1, 2, len(q))
        return counts * self.lsb

    def receive(self, msg, t: float) -> None:
        """A decoded message from the host, arriving at board time ``t`` (s)."""
        if isinstance(msg, CommandFrame | PlanFrame):
            if msg.n != len(self.joint_names):
                self.counters["commands_rejected"] += 1
                self.sticky_flags |= COMMAND_REJECTED  # a frame for another robot: keep the old command
                return
            self.sticky_flags &= ~COMMAND_REJECTED
            self.plan = msg if isinstance(msg, PlanFrame) else None
            self.command = msg.command if self.plan is not None else msg
            self.plan_end = t + self.plan.span_s if self.plan is not None else None
            self.counters["plans"] += self.plan is not None
            self.watchdog.kick(t if self.plan is None else self.plan_end)
            self.last_command_t = t
            self.last_command_sequence = msg.sequence
            self.counters["commands"] += 1
        elif isinstance(msg, ConfigFrame):
            try:
                if msg.has_limits:
                    self.limits = Limits.from_config(msg, self.joint_names)
                    self.limits.effort = np.minimum(self.limits.effort, self.effort_max)
                    self.limits_active = True
                if not 1000 <= msg.watchdog_timeout_us <= 1_000_000:
                    raise LimitsError(f"watchdog timeout {msg.watchdog_timeout_us} us outside 1 ms .. 1 s")
            except LimitsError:
                self.counters["configs_rejected"] += 1
                self.sticky_flags |= CONFIG_REJECTED
                return
            self.watchdog.timeout_s = msg.watchdog_timeout_us * 1e-6
            self.config_sequence = msg.sequence
            self.sticky_flags &= ~CONFIG_REJECTED
            self.counters["configs"] += 1

    def restart_clock(self) -> None:
        """The simulated time restarted (world reset): feedback is due at once, and the watchdog
        waits for a command on the new timeline (a kick from the old one would never expire)."""
        self._next_feedback = 0.0
        self._last_t = None
        self.watchdog.last_kick = None
        self.watchdog.state = "waiting"
        self.last_command_t = None
        self.plan = self.plan_end = None

    def step(self, t: float, q: np.ndarray, qd: np.ndarray,
             dt: float | None = None) -> tuple[np.ndarray, FeedbackFrame | None]:
        """One control period at board time ``t`` with the measured joint state; dt defaults to the time
        since the previous call."""
        if dt is None:
            dt = DEFAULT_DT if self._last_t is None or t <= self._last_t else t - self._last_t
        self._last_t = t
        q = self.measure(np.asarray(q, float))
        qd = np.asarray(qd, float)
        n = len(q)
        self._observe(qd, dt)
        expired = self.watchdog.check(t)
        if expired and not self._braking:
            self.counters["brake_events"] += 1
            self.last_brake = {"at": t, "last_command_at": self.last_command_t,
                               "last_command_sequence": self.last_command_sequence,
                               "plan_end": self.plan_end}
            self.brakes_after = (self.brakes_after + [self.last_command_sequence])[-BRAKES_KEPT:]
            self._next_feedback = t  # report the brake at once, not at the next feedback period
        self._braking = expired
        joint_flags = np.zeros(n, np.uint8)
        self.last_reasons = []
        if expired or self.command is None:
            effort = self._brake(qd, dt)
            self._muscles(q, q, qd, np.zeros(n, bool), dt)  # vent
            joint_flags[:] = JOINT_BRAKING
            self.last_safe = None  # on resume, rate limits start from where the axes are
        else:
            command = self.command if self.plan is None else self.plan.at(t - self.last_command_t)
            try:
                safe, self.last_reasons, joint_flags = enforce_with_flags(
                    command, SafetyState(q, qd, self.last_safe), self.limits, dt)
            except CommandRejectedError:  # cannot happen for accepted frames; brake if it ever does
                safe, joint_flags = CommandFrame.brake(0, n), np.full(n, JOINT_BRAKING, np.uint8)
            if self.last_reasons:
                self.counters["clamp_events"] += 1
            uses_position = (safe.mode == POSITION) | (safe.mode == IMPEDANCE) | (safe.mode == PNEUMATIC)
            self.last_safe = np.where(uses_position, safe.position, q)
            effort = self._control(safe, q, qd, dt)
            effort = self._limit_zone(effort, q, qd, safe.mode != BRAKE, joint_flags, dt)
        effort = np.clip(effort, -self.limits.effort, self.limits.effort)
        self._u_prev = effort
        feedback = None
        if t >= self._next_feedback:
            self._next_feedback = t + self.feedback_period_s - 1e-9
            feedback = self._feedback(t, q, qd, effort, expired, joint_flags)
        return effort, feedback

    def _limit_zone(self, effort: np.ndarray, q: np.ndarray, qd: np.ndarray, driven: np.ndarray,
                    joint_flags: np.ndarray, dt: float) -> np.ndarray:
        """Brake a driven joint whose braked stopping point (it coasts ``|v| m / c`` under the damper,
        ``v^2 m / 2 F`` where the motor's effort maximum F caps the damper, plus two control periods)
        lies beyond its position limit while it moves outward, so it stops
        before the hard stop whatever the setpoint or feed-forward asked: the joint gets the damper's
        effort or its controller's without its outward integral, whichever pushes it harder back
        inside (under a load such as the Z axes' weight the damper alone would let it sink on). The
        controller alone acts again once the joint no longer moves outward."""
        if not self.limits_active:
            return effort
        coast = self.inertia / self.brake_damping + np.abs(qd) * self.inertia / (2 * self.effort_max) + 2 * dt
        stop = q + qd * coast
        zone = driven & (((stop > self.limits.upper) & (qd > 0)) | ((stop < self.limits.lower) & (qd < 0)))
        onset = zone & ~self._in_zone
        self._in_zone = zone
        if not zone.any():
            return effort
        self.counters["limit_brakes"] += int(onset.sum())
        self.last_reasons += [f"limit_brake:{self.joint_names[i]}" for i in np.flatnonzero(zone)]
        joint_flags[zone] |= JOINT_BRAKING | JOINT_POSITION_LIMIT
        # The integral wound up while the joint lagged its setpoint: it pushes outward, drop it.
        effort = effort - np.where(zone & (self.integral * qd > 0), self.integral, 0.0)
        self.integral[zone & (self.integral * qd > 0)] = 0.0
        damper = self._damper(qd, dt)
        inward = np.where(qd > 0, np.minimum(effort, damper), np.maximum(effort, damper))
        return np.where(zone, inward, effort)

    def _brake(self, qd: np.ndarray, dt: float) -> np.ndarray:
        """Shorted windings: a viscous damper. The physics applies our effort one step late, so a stiff
        damper (Z: 2000 N s/m on ~1 kg, 2 ms steps) written as -c*qd would ring; integrate it
        implicitly instead, with the external load (the arm's weight) seen by a disturbance observer:
        u = -(c qd + b F) / (1 + b), b = c dt / m, which settles at qd = F / c like the real damper."""
        self.integral[:] = 0.0
        return self._damper(qd, dt)

    def _damper(self, qd: np.ndarray, dt: float) -> np.ndarray:
        b = self.brake_damping * dt / self.inertia
        return -(self.brake_damping * qd + b * self.f_ext) / (1.0 + b)

    def _observe(self, qd: np.ndarray, dt: float) -> None:
        """External joint load from the last step: what accelerated the axis beyond our own effort."""
        if self._qd_prev is not None:
            f = self.inertia * (qd - self._qd_prev) / dt - self._u_prev
            self.f_ext = 0.5 * self.f_ext + 0.5 * f
        self._qd_prev = qd.copy()

    def _control(self, c: CommandFrame, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        mode = c.mode.astype(np.uint8)
        self.integral[mode != self._prev_mode] = 0.0  # bumpless enough: a new mode starts from zero
        self._prev_mode = mode.copy()
        err = c.position - q
        verr = c.velocity - qd
        # Integral in effort units, narrowly clamped (thesis 6.3): position error for POSITION,
        # velocity error for VELOCITY.
        pos, vel, eff, imp = mode == POSITION, mode == VELOCITY, mode == EFFORT, mode == IMPEDANCE
        drive = pos * (self.ki * err) + vel * (self.kv * 5 * verr)
        self.integral = np.clip(self.integral + drive * dt, -self.i_clamp, self.i_clamp)
        effort = (pos * (self.kp * err + self.kd * verr) + vel * (self.kv * verr)
                  + (pos | vel) * self.integral + imp * (c.stiffness * err + c.damping * verr)
                  + (pos | vel | eff | imp) * c.effort)
        effort = np.where(mode == BRAKE, self._damper(qd, dt), effort)
        pneumatic = mode == PNEUMATIC
        muscle = self._muscles(c.position, q, qd, pneumatic, dt)
        return np.where(pneumatic, muscle, effort)

    def _muscles(self, target: np.ndarray, q: np.ndarray, qd: np.ndarray, active: np.ndarray,
                 dt: float) -> np.ndarray:
        """Muscle torques: ``active`` joints (PNEUMATIC mode) run the two-stage controller toward
        ``target``, every other joint vents both muscles (and its controller starts from zero when it
        enters the mode). The pressures integrate here; MuJoCo integrates the joint."""
        if not active.any() and not self.pressure.any():
            return np.zeros(len(q))
        ctl = self.pneumatic
        valves = -np.ones_like(self.pressure)
        if active.any():
            valves = np.where(active, ctl.valves(ctl.pressures(target, q, qd, dt), self.pressure, dt), valves)
        ctl.integral = np.where(active, ctl.integral, 0.0)
        ctl.p_integral = np.where(active, ctl.p_integral, 0.0)
        self.pressure = muscle_pressures(self.pressure, valves, self.fill_rate, self.leak, dt)
        return self.torque_per_bar * (self.pressure[0] - self.pressure[1])

    def _feedback(self, t: float, q: np.ndarray, qd: np.ndarray, effort: np.ndarray, expired: bool,
                  joint_flags: np.ndarray) -> FeedbackFrame:
        # Motor current: the q-axis current that makes this joint effort, plus sensing noise.
        current = effort / self.kt + self.rng.normal(0.0, self.current_noise_a, len(q))
        flags = self.sticky_flags
        flags |= WATCHDOG_EXPIRED if expired else 0
        flags |= NO_COMMAND_YET if self.command is None else 0
        flags |= LIMITS_ACTIVE if self.limits_active else 0
        flags |= CLAMPED if self.last_reasons else 0
        last = int(round(self.last_command_t * 1e6)) if self.last_command_t is not None else 0
        fb = FeedbackFrame(self.sequence & 0xFFFFFFFF, int(round(t * 1e6)), flags, q.copy(), qd.copy(),
                           current, last, self.last_command_sequence, self.config_sequence,
                           joint_flags.astype(np.uint8))
        self.sequence += 1
        return fb
