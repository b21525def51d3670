"""The PNEUMATIC mode of the simulated control board on the hand-arm in MuJoCo (thesis 7.3.2): the
board runs the two-stage PID against per-joint muscle pressures, MuJoCo integrates the fingers."""

from __future__ import annotations

import numpy as np
import pytest

from services.robot.board_sim import BoardSim
from services.robot.pneumatic import P_MAX, MusclePair, SingleStageController, muscle_pressures, pneumatic_params
from services.robot.safety import Limits
from services.world.sim import WorldSim
from shared.kinematics import load_robot
from shared.protocols import robot_board as rb

PNEUMATIC = ("index_j1", "index_j2", "index_j3", "thumb_j1")  # index_j3 follows index_j2 (mimic)


@pytest.fixture(scope="module")
def sim() -> WorldSim:
    return WorldSim(robot="hand_arm")


def start(sim: WorldSim, targets: dict[str, float]) -> tuple[list[str], rb.CommandFrame]:
    """From the home pose: the named joints in PNEUMATIC mode at their targets, the rest held in POSITION."""
    sim.reset(0)
    sim.set_robot_mode("robot")
    names = sim.joint_names
    q0, _ = sim.joint_state()
    mode, target = np.full(len(names), rb.Mode.POSITION, np.uint8), q0.copy()
    for j, v in targets.items():
        mode[names.index(j)], target[names.index(j)] = rb.Mode.PNEUMATIC, v
    return names, rb.CommandFrame(0, mode, target, *np.zeros((4, len(names))))


def run(sim: WorldSim, board: BoardSim, cmd: rb.CommandFrame | None, seconds: float, every=None):
    """Command at 250 Hz (None: silence), one board step per physics step; calls every(q, effort, fb)."""
    fbs = []
    for step in range(int(round(seconds / sim.physics_dt))):
        if cmd is not None and step % 2 == 0:
            board.receive(cmd, sim.time)
        q, qd = sim.joint_state()
        effort, fb = board.step(sim.time, q, qd, sim.physics_dt)
        sim.set_efforts(effort)
        sim.step(1)
        if fb is not None:
            fbs.append(fb)
        if every is not None:
            every(sim.joint_state()[0], effort, fb)
    return fbs


def test_pneumatic_fingers_reach_their_targets_in_the_hand_arm(sim):
    targets = {"index_j1": 0.8, "index_j2": 0.8, "index_j3": 0.8, "thumb_j1": 0.6}
    names, cmd = start(sim, targets)
    idx = [names.index(j) for j in targets]
    goal = np.array(list(targets.values()))
    # The limits the host installs (URDF): targets clamped into range, rate limited to 2 rad/s.
    board = BoardSim(names, Limits.from_model(load_robot("hand_arm")))
    trace, torques = [], []

    def record(q, effort, fb):
        trace.append(q[idx])
        torques.append((effort[idx], board.torque_per_bar[idx] * (board.pressure[0, idx] - board.pressure[1, idx])))

    fbs = run(sim, board, cmd, 1.5, record)
    trace = np.array(trace)
    err = np.abs(trace - goal)
    t = (np.arange(len(trace)) + 1) * sim.physics_dt
    settled = np.array([t[np.flatnonzero(err[:, k] > 0.05).max()] for k in range(len(idx))])
    print(f"within 0.05 rad after {settled} s, overshoot {trace.max(0) - goal} rad, error at 1.5 s {err[-1]} rad")
    assert (settled < 0.6).all()  # a 2 rad/s ramp of 0.6-0.8 rad takes 0.3-0.4 s of it
    assert (trace.max(0) - goal < 0.1).all()
    assert (err[-1] < 0.03).all()
    q, _ = sim.joint_state()
    assert q[names.index("index_j3")] == pytest.approx(q[names.index("index_j2")], abs=2e-3)
    # The applied effort is the muscle torque, which the feedback reports as the joint's current.
    effort, muscle = np.array(torques).transpose(1, 0, 2)
    np.testing.assert_allclose(effort, muscle, atol=1e-12)
    assert np.abs(muscle).max() > 0.1
    fb = fbs[-1]
    np.testing.assert_allclose(fb.current[idx] * board.kt[idx], effort[-1], atol=5 * board.current_noise_a * 0.05)
    assert not fb.joint_flags[idx].any() and not fb.watchdog_expired


def single_stage(sim: WorldSim, joint: str, target: float, seconds: float) -> np.ndarray:
    """The original scheme on the same finger in MuJoCo: a position PI straight onto the valves."""
    names = sim.joint_names
    i, j3 = names.index(joint), names.index(joint.replace("j2", "j3"))
    pp = pneumatic_params(joint)
    ctl, pair = SingleStageController(), MusclePair(p=np.zeros(2))
    others = BoardSim(names)
    q0, _ = sim.joint_state()
    hold = rb.CommandFrame.hold(0, q0)
    hold.position[[i, j3]] = target
    for step in range(int(round(seconds / sim.physics_dt))):
        if step % 2 == 0:
            others.receive(hold, sim.time)
        q, qd = sim.joint_state()
        effort, _ = others.step(sim.time, q, qd, sim.physics_dt)
        pair.q = q[i]
        pair.p = muscle_pressures(pair.p, ctl.command(target, pair, sim.physics_dt), pp.fill_rate, pp.leak,
                                  sim.physics_dt)
        effort[i] = pp.torque_per_bar * (pair.p[0] - pair.p[1])
        sim.set_efforts(effort)
        sim.step(1)
    return pair.p


def test_against_the_joint_stop_the_differential_settles_at_stiffness_times_error(sim):
    """index_j2 held at 2.0 rad, beyond its stop at 1.57 rad (power-up limits: no position clamp), so
    the MuJoCo joint limit is the obstacle: the upper stage's differential settles near stiffness x
    error (plus at most the clamped integral) instead of filling the flexor; the single-stage scheme
    fills it to P_MAX."""
    names, cmd = start(sim, {"index_j2": 2.0, "index_j3": 2.0})
    i = names.index("index_j2")
    board = BoardSim(names)
    diffs, qs = [], []
    run(sim, board, cmd, 3.0, lambda q, e, fb: (diffs.append(board.pressure[0, i] - board.pressure[1, i]),
                                                 qs.append(q[i])))
    late, q_late = np.array(diffs[-500:]), np.array(qs[-500:])
    pp = pneumatic_params("index_j2")
    expected = pp.stiffness * (2.0 - q_late.mean())
    print(f"at the stop q = {q_late.mean():.3f} rad, differential {late.mean():.3f} bar "
          f"(stiffness x error {expected:.3f}), pressures {board.pressure[:, i]}")
    assert q_late.mean() == pytest.approx(1.57, abs=0.03)  # it does press on the (soft) stop
    assert np.ptp(late) < 0.05 and late[-1] <= late[0] + 0.01  # settled, not growing
    # The integral adds at most i_clamp; the lower stage's own integral, wound up by the fast move,
    # still leaves a few hundredths of a bar after 3 s.
    assert 0.0 <= late.mean() - expected <= pp.i_clamp + 0.1
    assert board.pressure[:, i].max() < P_MAX - 0.5  # far from saturation
    sim.reset(0)
    sim.set_robot_mode("robot")
    p = single_stage(sim, "index_j2", 2.0, 3.0)
    print(f"single stage: pressures {p}")
    assert p[0] > P_MAX - 0.05


def test_watchdog_brakes_a_pneumatic_finger_and_vents_its_muscles(sim):
    names, cmd = start(sim, {"index_j2": 0.8, "index_j3": 0.8})
    i = names.index("index_j2")
    board = BoardSim(names)
    run(sim, board, cmd, 0.5)
    assert board.pressure[:, i].max() > 1.0
    t_silent = sim.time
    efforts = []
    fbs = run(sim, board, None, 0.7, lambda q, e, fb: efforts.append(e[i]))
    first = next(fb for fb in fbs if fb.watchdog_expired)
    assert first.joint_flags[i] & rb.JOINT_BRAKING
    assert first.timestamp_us * 1e-6 - t_silent <= 0.010 + 2 * sim.physics_dt
    assert board.brake_events == 1
    np.testing.assert_array_equal(board.pressure[:, i], 0.0)  # both muscles vented
    _, qd = sim.joint_state()
    np.testing.assert_allclose(efforts[-1], board._damper(qd, sim.physics_dt)[i], atol=0.05)  # the usual damper
    run(sim, board, cmd, 1.0)  # the next command resumes the mode from vented muscles
    assert sim.joint_state()[0][i] == pytest.approx(0.8, abs=0.03)


def test_the_service_commands_pneumatic_fingers_only_on_a_robot_that_has_them():
    from services.robot.service import command_modes

    names = load_robot("hand_arm").joint_names
    modes = command_modes(names, "pneumatic")
    assert [n for n, m in zip(names, modes, strict=True) if m == rb.Mode.PNEUMATIC] == names[6:]
    assert (modes[:6] == rb.Mode.POSITION).all() and (command_modes(names) == rb.Mode.POSITION).all()
    with pytest.raises(ValueError, match="no joint of this robot has a pneumatic drive"):
        command_modes(load_robot("workcell").joint_names, "pneumatic")
    with pytest.raises(ValueError, match="finger_mode must be"):
        command_modes(names, "hydraulic")
