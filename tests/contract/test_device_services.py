"""Contract tests of the device services: each runs as its own process and is seen only through
Zenoh; the test plays the device on a pty, speaking the real byte protocol."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from services.glove.layout import DEFAULT_CELLMAP
from services.robot.safety import WATCHDOG_TIMEOUT_S, soft_limits
from services.robot.service import VELOCITY_SLACK
from services.world.model import PHYSICS_DT
from services.world.pty_device import PtyDevice
from shared import msgs
from shared.kinematics import load_robot
from shared.protocols import robot_board as rb
from shared.protocols import tactile
from tests.conftest import BoardHost, ServiceProcess, query_json, wait_for, wait_until, write_deployment
from tests.robot_board import board_feedback


def subscribe(session, key, msgtype, out: list):
    return session.declare_subscriber(key, lambda s: out.append(msgs.deserialize(s.payload.to_bytes(), msgtype)))


def world_time_passes(now, seconds: float) -> None:
    """Waits until the world's clock, as ``now()`` reads it off its messages, advanced by ``seconds``:
    robust to a world that runs slower than real time on a loaded machine."""
    t0 = now()
    wait_until(lambda: now() >= t0 + seconds, 60, f"{seconds} s of world time")


def test_glove_publishes_calibrated_pressure_counts_garbage_and_reconnects(router, tmp_path):
    endpoint, session = router
    port = tmp_path / "glove-left"
    dev = PtyDevice(port)
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"glove": {"left": {"port": str(port)}}})
    svc = ServiceProcess("glove", dep, "left", tmp_path / "glove.log")
    got: list = []
    _sub = subscribe(session, "xm/glove/left/tactile", "xm_msgs/msg/Tactile", got)
    try:
        from services.glove.layout import region_means, region_pressure_kpa
        from services.glove.sensor_model import GloveSensorModel

        model = GloveSensorModel(0)  # the factory calibration of glove 0 (left)
        forces = np.array([2.0, 6.0, 0.0, 0.0, 0.0, 0.0])
        assert wait_for(lambda: query_json(session, "xm/glove/left/@health"), 20), svc.output()

        def link() -> dict:
            return query_json(session, "xm/glove/left/@health")[0]["link"]

        def send(seq: int) -> None:
            dev.write(tactile.encode_frame(tactile.TactileFrame(seq, seq * 1000, model.impedance(forces, seq * 1e-3))))

        wait_until(lambda: (send(0), got)[1], 10, lambda: f"the first frame published: {svc.output()}")
        dev.write(b"\x00garbage\xa5\x5a\x01\xff\xff noise")
        for seq in range(1, 20):  # each frame published before the next is sent: the pty never overflows
            send(seq)
            wait_until(lambda seq=seq: got[-1].sequence == seq, 10, f"frame {seq} published")
        assert dev.dropped_bytes == 0 and [m.sequence for m in got if m.sequence] == list(range(1, 20))
        means = region_means(np.asarray(got[-1].pressure).reshape(16, 16))
        np.testing.assert_allclose(means[:2], region_pressure_kpa(forces)[:2], rtol=0.1)
        health = query_json(session, "xm/glove/left/@health")[0]
        assert health["decoder"]["bytes_discarded"] > 0 and health["decoder"]["resyncs"] >= 1
        assert health["layout"]["cellmap"].endswith("models/skin/glove_cellmap.json"), "the shipped layout"
        assert health["layout"]["cells"]["palm"] == 30
        # what scheduling the reader and the kernel's tty workers got depends on the host's permissions
        assert health["link"]["reader_priority"] in ("fifo", "nice", "normal")
        assert isinstance(health["tty_workers_raised"], int) and health["tty_workers_raised"] >= 0
        # The port disappears and comes back: the service reconnects and reports the gap (how fast:
        # bench/devices.py).
        dev.close()
        wait_until(lambda: not link()["connected"], 10, "the service to see the port vanish")
        dev = PtyDevice(port)
        wait_until(lambda: link()["connects"] >= 2, 10, "the service to reconnect")
        assert link()["disconnects"] == 1 and link()["last_gap_s"] > 0
        n = len(got)
        send(100)
        wait_until(lambda: len(got) > n, 10, "a frame after the reconnection")
        assert got[-1].sequence == 100
        assert query_json(session, "xm/glove/left/@health")[0]["decoder"]["sequence_gaps"] >= 1
    finally:
        assert svc.stop() in (0, -15), svc.output()
        dev.close()


def test_glove_refuses_a_broken_cell_map_and_reports_it_in_health(router, tmp_path):
    """A cell map in which two sensors claim one crossing: the glove stays up, opens no port,
    publishes nothing, and @health names the file and the problem."""
    endpoint, session = router
    d = json.loads(DEFAULT_CELLMAP.read_text())
    d["sensors"][1]["cells"][0].update(row=0, col=0)  # the thumb claims a palm crossing
    bad = tmp_path / "clash.json"
    bad.write_text(json.dumps(d))
    dep = write_deployment(tmp_path / "d.toml", endpoint,
                           {"glove": {"left": {"port": str(tmp_path / "glove-left"), "cellmap": str(bad)}}})
    svc = ServiceProcess("glove", dep, "left", tmp_path / "glove.log")
    try:
        assert wait_for(lambda: query_json(session, "xm/glove/left/@health"), 20), svc.output()
        health = query_json(session, "xm/glove/left/@health")[0]
        assert health["status"] == "error" and "clash.json" in health["message"], health
        assert "thumb: cell (0, 0) is also palm's" in health["layout"]["error"]
        assert health["errors"]["bad_cellmap"] == 1 and "link" not in health
    finally:
        assert svc.stop() in (0, -15), svc.output()


def test_robot_follows_trajectories_rejects_nan_and_stops_commanding_without_feedback(router, tmp_path):
    endpoint, session = router
    port = tmp_path / "board"
    dev = PtyDevice(port)
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"robot": {"workcell": {"port": str(port)}}})
    svc = ServiceProcess("robot", dep, "workcell", tmp_path / "robot.log")
    model = load_robot("workcell")
    names = model.joint_names
    n = len(names)
    commands: list = []
    states: list = []
    _sub = subscribe(session, "xm/robot/workcell/state", "sensor_msgs/msg/JointState", states)
    q = np.zeros(n)
    board = board_feedback(dev, svc, commands, q)

    def health() -> dict:
        return query_json(session, "xm/robot/workcell/@health")[0]

    try:
        assert wait_for(lambda: query_json(session, "xm/robot/workcell/@health"), 20), svc.output()
        board(lambda: states and len(commands) >= 5, 20, "state published and commands sent")
        soft = soft_limits(load_robot("workcell"))
        # holds where it is, inside the soft limits (0 is the hard lower limit of the Z axes and fingers)
        assert all(np.allclose(c.position, np.clip(0.0, soft.lower, soft.upper)) for c in commands[:5])
        pub = session.declare_publisher("xm/trajopt/main/trajectory")

        def trajectory(value: float):
            now = time.time()
            points = [msgs.make("trajectory_msgs/msg/JointTrajectoryPoint", positions=np.full(n, value),
                                velocities=np.zeros(0), accelerations=np.zeros(0), effort=np.zeros(0),
                                time_from_start=msgs.make("builtin_interfaces/msg/Duration", sec=k, nanosec=0))
                      for k in range(3)]
            return msgs.make("trajectory_msgs/msg/JointTrajectory", header=msgs.header(now), joint_names=names,
                             points=points)

        # The subscription keeps only the latest: each one is seen before the next is sent.
        # The NaN trajectory is refused at the subscription, before the follower sees it.
        rejected = lambda: health()["rejected"].get("xm/trajopt/main/trajectory", {})  # noqa: E731
        pub.put(msgs.serialize(trajectory(float("nan"))))
        wait_until(lambda: rejected().get("non_finite"), 10, "the NaN trajectory rejected")
        pub.put(b"not cdr at all")
        wait_until(lambda: any(k.startswith("malformed") for k in health()["errors"]), 10, "garbage counted")
        start = len(commands)
        pub.put(msgs.serialize(trajectory(5.0)))  # far outside every joint's range
        reachable = np.clip(5.0, soft.lower, soft.upper)
        board(lambda: np.allclose(commands[-1].position, reachable, atol=1e-6), 30,
              "the commands to stop at the soft joint limits")
        assert rejected().get("non_finite") == 1
        moving = np.array([c.position for c in commands[start - 1:]])
        steps = np.abs(np.diff(moving, axis=0))
        # each step within the velocity limit over the longest gap between two commands (with slack)
        max_gap_s = health()["command_stream"]["max_gap_ms"] * 1e-3
        assert np.all(steps <= soft.velocity * VELOCITY_SLACK * max_gap_s + 1e-6), "velocity limits enforced"
        assert np.all(steps.max(axis=0) >= 0.5 * soft.velocity * BoardHost.COMMAND_PERIOD_S), "a ramp at the limit"
        # The board vanishes: the host stops commanding (the board's own watchdog brakes).
        dev.close()
        wait_until(lambda: not health()["link"]["connected"], 10, "the service to see the board vanish")
    finally:
        assert svc.stop() in (0, -15), svc.output()
        dev.close()


def test_world_board_brakes_after_10ms_of_silence_on_every_trial(router, tmp_path):
    """The test is the host on the world's simulated control board (a pty): command bursts, then
    silence; every time the board reports a brake naming the last command, after its 10 ms watchdog
    timeout and no later than one physics step past it (board time: the board waits for a pty that
    may still hold a command, services/world/devices.py). The spread of it: bench/devices.py."""
    endpoint, session = router
    run = tmp_path / "run"
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"world": {"sim": {"robot_port": str(run / "board")}}},
                           clock="sim")
    world = ServiceProcess("world", dep, "sim", tmp_path / "world.log")
    try:
        wait_until(lambda: (run / "board").exists(), 30, lambda: f"the board's pty: {world.output()}")
        host = BoardHost(run / "board")
        n = len(load_robot("workcell").joint_names)
        cmd = rb.CommandFrame(0, np.full(n, rb.Mode.POSITION, np.uint8), *np.zeros((5, n)))
        latencies = [host.brake_trial(cmd, 0.03 + 0.02 * (trial % 3)) for trial in range(5)]
        host.close()
        # The board reports whole microseconds (each time rounded), so a brake 10.0004 ms after reads 10.000.
        assert min(latencies) > WATCHDOG_TIMEOUT_S - 1e-6, f"braked {min(latencies) * 1e3:.3f} ms after a command"
        assert max(latencies) <= WATCHDOG_TIMEOUT_S + PHYSICS_DT + 1e-6, f"braked {max(latencies) * 1e3:.1f} ms after"
    finally:
        assert world.stop() in (0, -15), world.output()


def test_robot_service_suspended_mid_stream_the_world_board_brakes_in_time(router, tmp_path):
    """The robot service commands the world's board; the test suspends the service's process
    (SIGSTOP: its command stream stops mid-stream). The board plays the last plan it got to its end
    and brakes more than 10 ms and at most 10 ms plus one physics step after that end in board time;
    resumed, the service feeds the watchdog again."""
    endpoint, session = router
    port = str(tmp_path / "run" / "board")
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"world": {"sim": {"robot_port": port}},
                                                          "robot": {"workcell": {"port": port}}}, clock="sim")
    world = ServiceProcess("world", dep, "sim", tmp_path / "world.log")
    robot = None
    board = lambda: query_json(session, "xm/world/sim/@health")[0]["devices"]["robot"]  # noqa: E731
    try:
        wait_until(lambda: Path(port).exists(), 60, lambda: f"the board's pty: {world.output()}")
        robot = ServiceProcess("robot", dep, "workcell", tmp_path / "robot.log")
        health = lambda: (query_json(session, "xm/robot/workcell/@health") or [{}])[0]  # noqa: E731
        wait_until(lambda: health().get("watchdog") == "ok", 60, lambda: f"commands: {robot.output()}")
        before = board()["watchdog_brakes"]
        os.killpg(robot.proc.pid, signal.SIGSTOP)
        try:
            dev = wait_until(lambda: (lambda d: d if d["watchdog_brakes"] > before else None)(board()), 10,
                             "the board's brake")
        finally:
            os.killpg(robot.proc.pid, signal.SIGCONT)
        brake = dev["last_brake"]
        assert dev["plans"] > 0 and brake["plan_end"] > brake["last_command_at"], dev
        after = brake["at"] - brake["plan_end"]
        assert WATCHDOG_TIMEOUT_S < after <= WATCHDOG_TIMEOUT_S + PHYSICS_DT + 1e-6, f"{after * 1e3:.2f} ms after"
        wait_until(lambda: health().get("watchdog") == "ok", 30, "commands again after SIGCONT")
    finally:
        if robot is not None:
            assert robot.stop() in (0, -15), robot.output()
        assert world.stop() in (0, -15), world.output()


def test_world_with_the_hand_arm_serves_its_board_and_follows_a_position_command(router, tmp_path):
    """A world built with robot="hand_arm" hosts the board for the hand-arm's 19 joints on its pty:
    the test, as the host, commands a new arm and finger pose and sees the feedback get there, with
    each coupled distal joint following its middle joint; a frame for the gantry's 10 joints is refused."""
    endpoint, session = router
    run = tmp_path / "run"
    dep = write_deployment(tmp_path / "d.toml", endpoint,
                           {"world": {"sim": {"robot": "hand_arm", "robot_port": str(run / "board")}}}, clock="sim")
    world = ServiceProcess("world", dep, "sim", tmp_path / "world.log")
    try:
        wait_until(lambda: (run / "board").exists(), 30, lambda: f"the board's pty: {world.output()}")
        host = BoardHost(run / "board")
        feedback = host.feedback
        names = load_robot("hand_arm").joint_names
        n = len(names)
        host.stream(None, lambda: feedback, 10, "feedback from the board")
        assert len(feedback[-1].position) == n, world.output()
        start = feedback[-1].position.copy()
        target = start.copy()
        target[names.index("elbow")] -= 0.2
        target[names.index("wrist_3")] += 0.3
        for finger in ("index", "middle"):
            target[names.index(f"{finger}_j2")] = target[names.index(f"{finger}_j3")] = 0.7
        mode = np.full(n, rb.Mode.POSITION, np.uint8)
        host.stream(rb.CommandFrame(0, mode, target, np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)),
                    lambda: np.abs(feedback[-1].position - target).max() < 0.01, 30, "the commanded pose")
        last = feedback[-1]
        assert not last.watchdog_expired and last.last_command_sequence > 0
        for finger in ("index", "middle"):
            assert abs(last.position[names.index(f"{finger}_j3")] - last.position[names.index(f"{finger}_j2")]) < 0.01
        gantry = len(load_robot("workcell").joint_names)
        host.stream(rb.CommandFrame(0, np.full(gantry, rb.Mode.POSITION, np.uint8), *np.zeros((5, gantry))),
                    lambda: feedback[-1].flags & rb.COMMAND_REJECTED, 10, "the gantry's frame refused")
        host.close()
        health = query_json(session, "xm/world/sim/@health")[0]
        assert health["devices"]["robot"]["feedback_frames"] >= len(feedback) > 0  # it counts what it sent
    finally:
        assert world.stop() in (0, -15), world.output()


@pytest.mark.parametrize("finger_mode", ["position", "pneumatic"])
def test_robot_service_drives_the_worlds_hand_arm_and_publishes_its_state_key(router, tmp_path, finger_mode):
    """The robot service, instance hand_arm, on the world's simulated hand-arm board: it publishes
    xm/robot/hand_arm/state with the 19 joints, holds the arm where it stands, and follows a trajectory
    (fingers on the board's position loops, or on its two-stage pneumatic PID)."""
    endpoint, session = router
    run = tmp_path / "run"
    port = str(run / "board")
    dep = write_deployment(tmp_path / "d.toml", endpoint, {
        "world": {"sim": {"robot": "hand_arm", "robot_port": port}},
        "robot": {"hand_arm": {"robot": "hand_arm", "port": port, "finger_mode": finger_mode}}}, clock="sim")
    world = ServiceProcess("world", dep, "sim", tmp_path / "world.log")
    names = load_robot("hand_arm").joint_names
    states: list = []
    _sub = subscribe(session, "xm/robot/hand_arm/state", "sensor_msgs/msg/JointState", states)
    try:
        assert wait_for(lambda: (run / "board").exists(), 30), world.output()
        robot = ServiceProcess("robot", dep, "hand_arm", tmp_path / "robot.log")
        try:
            wait_until(lambda: len(states) > 20, 30, lambda: f"the robot's state: {robot.output()}")
            assert list(states[-1].name) == names
            state_time = lambda: msgs.stamp_seconds(states[-1].header.stamp)  # noqa: E731

            # the hold starts with the commands: until they flow the board brakes and the fingers sag
            wait_until(lambda: (query_json(session, "xm/robot/hand_arm/@health") or [{}])[0].get("watchdog") == "ok",
                       30, lambda: f"the robot's commands: {robot.output()}")
            world_time_passes(state_time, 0.2)
            if finger_mode == "pneumatic":
                world_time_passes(state_time, 1.0)  # the vented muscles fill to their bias (a sag)
            held = np.asarray(states[-1].position)
            world_time_passes(state_time, 1.0)  # how long the arm is watched
            drift = np.abs(np.asarray(states[-1].position) - held)
            assert drift.max() < 0.01, f"the arm holds where it stands: {names[drift.argmax()]} moved {drift.max()}"
            goal = held.copy()
            goal[names.index("shoulder_pan")] += 0.2
            goal[names.index("index_j2")] = goal[names.index("index_j3")] = 0.5
            points = [msgs.make("trajectory_msgs/msg/JointTrajectoryPoint", positions=goal, velocities=np.zeros(0),
                                accelerations=np.zeros(0), effort=np.zeros(0),
                                time_from_start=msgs.make("builtin_interfaces/msg/Duration", sec=k, nanosec=0))
                      for k in range(3)]
            clock = query_json(session, "xm/robot/hand_arm/@health")[0]["clock"]
            session.put("xm/trajopt/main/trajectory", msgs.serialize(msgs.make(
                "trajectory_msgs/msg/JointTrajectory", header=msgs.header(clock), joint_names=names, points=points)))
            assert wait_for(lambda: np.abs(np.asarray(states[-1].position) - goal).max() < 0.01, 15), robot.output()
            board = query_json(session, "xm/world/sim/@health")[0]["devices"]["robot"]
            fingers = sum(n.startswith(("thumb_", "index_", "middle_", "ring_")) for n in names)
            assert board["command_modes"] == ({"position": len(names)} if finger_mode == "position" else
                                              {"position": len(names) - fingers, "pneumatic": fingers})
            assert (board["muscle_pressure_max_bar"] > 1.0) == (finger_mode == "pneumatic")
        finally:
            assert robot.stop() in (0, -15), robot.output()
    finally:
        assert world.stop() in (0, -15), world.output()


def test_glove_registers_masks_and_imu_through_the_worlds_readout_module(router, tmp_path):
    """The world's simulated readout module answers register commands on its pty like the FPGA
    core; the glove service exposes them as @cmd/register and honours masks, run bit and IMU."""
    endpoint, session = router
    run = tmp_path / "run"
    port = str(run / "glove-left")
    dep = write_deployment(tmp_path / "d.toml", endpoint, {
        "world": {"sim": {"glove_ports": [port]}},
        "glove": {"left": {"port": port, "publish_imu": True}}}, clock="sim")
    world = ServiceProcess("world", dep, "sim", tmp_path / "world.log")
    got: list = []
    imu: list = []
    clock: list = []
    _subs = [subscribe(session, "xm/glove/left/tactile", "xm_msgs/msg/Tactile", got),
             subscribe(session, "xm/glove/left/imu", "xm_msgs/msg/Imu", imu),
             subscribe(session, "xm/clock", "rosgraph_msgs/msg/Clock", clock)]
    try:
        assert wait_for(lambda: (run / "glove-left").exists(), 30), world.output()
        glove = ServiceProcess("glove", dep, "left", tmp_path / "glove.log")
        try:
            def register(name: str, value: int | None = None) -> dict:
                replies = query_json(session, "xm/glove/left/@cmd/register",
                                     {"name": name, **({"value": value} if value is not None else {})}, timeout=3)
                return replies[0] if replies else {}

            assert wait_for(lambda: got, 30), glove.output()
            assert register("id") == {"ok": True, "name": "id", "address": tactile.REG_ID,
                                      "value": tactile.DEVICE_ID, "status": "ok"}
            assert register("id", 5)["status"] == "read_only"
            assert "unknown register" in register("bogus")["error"]
            assert register("window", 128)["value"] == 128 and register("window")["value"] == 128
            # Only reception lines 0 and 1: every other column is masked.
            assert register("rx_enable", 0b11)["ok"]
            assert wait_for(lambda: got and not np.asarray(got[-1].mask).reshape(16, 16)[:, 2:].any(), 5)
            assert np.asarray(got[-1].mask).reshape(16, 16)[:, :2].any()
            seen = got[-1].sequence  # frames keep arriving while the register query is answered
            assert register("frame_count")["value"] >= seen
            # IMU on: samples of a moving hand under gravity.
            assert register("imu_enable", 1)["ok"]
            assert wait_for(lambda: len(imu) >= 20, 10), glove.output()
            accel = np.array([np.asarray(m.accel)[:3] for m in imu[5:]])
            assert np.all(np.isfinite(accel)) and 5.0 < np.median(np.linalg.norm(accel, axis=1)) < 15.0
            # Run bit off: the stream stops; on: it resumes. Watched over world time (the sim clock).
            world_time = lambda: msgs.stamp_seconds(clock[-1].clock)  # noqa: E731
            assert register("control", 0)["ok"]
            world_time_passes(world_time, 0.2)  # frames already on their way
            n = len(got)
            world_time_passes(world_time, 0.5)  # ~50 frame periods
            assert len(got) == n, "frames kept coming with control.run = 0"
            assert register("control", 1)["ok"]
            wait_until(lambda: len(got) > n + 5, 10, "the stream to resume")
        finally:
            assert glove.stop() in (0, -15), glove.output()
    finally:
        assert world.stop() in (0, -15), world.output()
