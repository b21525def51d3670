"""The robot's arm gate (services/robot/service.py): the robot service as a process, the test as its
control board on a pty. A disarmed robot holds whatever trajectory arrives; armed it follows;
disarm and the dashboard's stop (@cmd/hold {"disarm": true}) hold it again with nothing upstream
running (no policy, no trajopt)."""

from __future__ import annotations

import time

import numpy as np

from services.world.pty_device import PtyDevice
from shared import msgs
from shared.kinematics import load_robot
from tests.conftest import ServiceProcess, query_json, wait_for, write_deployment
from tests.robot_board import board_feedback

ROBOT = "xm/robot/workcell"


def test_the_robot_moves_only_while_armed_and_stop_holds_it(router, tmp_path):
    endpoint, session = router
    port = tmp_path / "board"
    dev = PtyDevice(port)
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"robot": {"workcell": {
        "port": str(port), "start_armed": False}}})
    svc = ServiceProcess("robot", dep, "workcell", tmp_path / "robot.log")
    names = load_robot("workcell").joint_names
    n = len(names)
    commands: list = []
    q = np.zeros(n)
    board = board_feedback(dev, svc, commands, q)

    def health() -> dict:
        return query_json(session, f"{ROBOT}/@health")[0]

    def ask(verb: str, payload: dict) -> dict:
        return query_json(session, f"{ROBOT}/@cmd/{verb}", payload)[0]

    pub = session.declare_publisher("xm/trajopt/main/trajectory")

    def send_trajectory() -> None:  # every joint towards 0.3 (inside every soft limit), over 2 s
        points = [msgs.make("trajectory_msgs/msg/JointTrajectoryPoint", positions=np.full(n, 0.3 * k / 2),
                            velocities=np.zeros(0), accelerations=np.zeros(0), effort=np.zeros(0),
                            time_from_start=msgs.make("builtin_interfaces/msg/Duration", sec=k, nanosec=0))
                  for k in range(3)]
        pub.put(msgs.serialize(msgs.make("trajectory_msgs/msg/JointTrajectory", header=msgs.header(time.time()),
                                         joint_names=names, points=points)))

    def spread() -> float:
        """How far the commands since ``mark`` moved (max over joints)."""
        pos = np.array([c.position for c in commands[mark:]])
        return float(np.abs(pos - pos[0]).max()) if len(pos) > 1 else 0.0

    try:
        assert wait_for(lambda: query_json(session, f"{ROBOT}/@health"), 20), svc.output()
        board(lambda: len(commands) >= 5, 20, "commands sent")
        assert health()["armed"] is False and ask("arm", {}) == {"ok": True, "armed": False}
        # disarmed: a trajectory is ignored (counted), the commands stay where they are
        mark = len(commands)
        send_trajectory()
        board(lambda: health()["errors"].get("ignored_disarmed"), 10, "the trajectory ignored")
        board(lambda: len(commands) > mark + 100, 10, "commands while disarmed")
        assert spread() == 0.0, "a disarmed robot does not move"
        # armed: the next trajectory is followed
        assert ask("arm", {"armed": True}) == {"ok": True, "armed": True}
        mark = len(commands)
        send_trajectory()
        board(lambda: spread() > 0.05, 20, "the armed robot following the trajectory")
        # the dashboard's stop: hold and disarm at once; the commands stop moving
        assert ask("hold", {"disarm": True}) == {"ok": True, "armed": False}
        held = len(commands)
        board(lambda: len(commands) > held + 50, 10, "commands after the stop")
        mark = held + 5  # the rate limiter may finish the step under way
        board(lambda: len(commands) > mark + 100, 10, "commands while stopped")
        assert spread() < 1e-9, "stopped: the robot holds"
        send_trajectory()  # and stays put whatever arrives
        board(lambda: health()["errors"].get("ignored_disarmed", 0) >= 2, 10, "the trajectory ignored again")
        board(lambda: len(commands) > mark + 200, 10, "more commands")
        assert spread() < 1e-9
        # disarm through @cmd/arm holds alike; a bad value is refused and counted
        assert ask("arm", {"armed": True})["armed"] and ask("arm", {"armed": False}) == {"ok": True, "armed": False}
        bad = ask("arm", {"armed": "yes"})
        assert bad["ok"] is False and "armed must be true or false" in bad["error"]
        assert health()["armed"] is False
    finally:
        pub.undeclare()
        assert svc.stop() in (0, -15), svc.output()
        dev.close()
