"""Spurious brakes and clamps of the robot path: the world (simulated control board on its pty,
sim clock) and the robot service as processes, a trajopt-like source publishing 1 s trajectories
at 10 Hz that sweep every joint at up to ``--speed`` of its velocity limit, inside the joint
limits. Counts per minute, from the services' @health: the board's watchdog brakes (no command
for over 10 ms of board time; after a plan, 10 ms past its last knot), its limit brakes, the host's
velocity and position clamps, the longest gap between two frames the robot service sent and the
gaps over 10 ms that a plan bridged.

Each brake is matched, by the sequence of the last frame before it, to the host's own record of
gaps in its command stream: a brake after a gap the host left (longer than the plan's look-ahead
plus 10 ms, less 1 ms: the board hears a frame up to 1 ms late) is a real one, any other is
*spurious* (the board, the pty or the world starved the watchdog while the host kept sending,
which counts too). Then the command stream stops (the robot process is suspended with SIGSTOP)
and the board time from the end of the last plan to the brake is recorded: the watchdog must still
brake within 10 ms plus one physics step of it.

Runs three times: with plans (the deployments' default) on the host as it is ("idle": other jobs
on the machine are not stopped, so say what else ran), with plans and ``--load N`` CPU-bound
processes beside it (default: one per core), and, as the baseline, single commands at 250 Hz under
the same load; writes all three to .bench/robot.json. Target: 0 spurious watchdog brakes and 0
clamps per minute with plans, idle and loaded; every brake counts, whatever the host did.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere

from bench.glove import start_load, stop_load  # noqa: E402
from services.robot.safety import WATCHDOG_TIMEOUT_S, soft_limits  # noqa: E402
from services.world.model import PHYSICS_DT  # noqa: E402
from shared import msgs  # noqa: E402
from shared.kinematics import load_robot  # noqa: E402
from shared.runtime import open_router  # noqa: E402
from tests.conftest import ServiceProcess, free_endpoint, query_json, wait_for, write_deployment  # noqa: E402

KNOTS, KNOT_S, RATE_HZ = 20, 0.05, 10.0


def trajectory(names: list[str], t0: float, center: np.ndarray, amplitude: np.ndarray, period: float):
    """Knots of a sine sweep around ``center`` from sim time ``t0`` (as trajopt publishes them)."""
    points = []
    for k in range(KNOTS):
        t = t0 + k * KNOT_S
        q = center + amplitude * np.sin(2 * np.pi * t / period)
        v = amplitude * 2 * np.pi / period * np.cos(2 * np.pi * t / period)
        points.append(msgs.make("trajectory_msgs/msg/JointTrajectoryPoint", positions=q, velocities=v,
                                accelerations=np.zeros(0), effort=np.zeros(0),
                                time_from_start=msgs.make("builtin_interfaces/msg/Duration", sec=int(k * KNOT_S),
                                                          nanosec=int(round((k * KNOT_S % 1) * 1e9)))))
    return msgs.make("trajectory_msgs/msg/JointTrajectory", header=msgs.header(t0, "world"), joint_names=names,
                     points=points)


PLANS = {"command_rate_hz": 125.0, "lookahead_s": 0.112, "knot_spacing_s": 0.016}
SINGLE_COMMANDS = {"command_rate_hz": 250.0, "lookahead_s": 0.0}


def run_once(seconds: float, load: int, speed: float, stream: dict) -> dict:
    endpoint = free_endpoint()
    router = open_router(endpoint)
    tmp = Path(tempfile.mkdtemp(prefix="bench-robot-"))
    port = str(tmp / "run" / "board")
    dep = write_deployment(tmp / "d.toml", endpoint, {"world": {"sim": {"robot_port": port}},
                                                      "robot": {"workcell": {"port": port, **stream}}}, clock="sim")
    world = ServiceProcess("world", dep, "sim", tmp / "world.log")
    robot = None
    hogs: list = []
    try:
        if not wait_for(lambda: Path(port).exists(), 60):
            raise RuntimeError(f"world did not start:\n{world.output()[-2000:]}")
        robot = ServiceProcess("robot", dep, "workcell", tmp / "robot.log")
        health = lambda s, i: (query_json(router, f"xm/{s}/{i}/@health") or [{}])[0]  # noqa: E731
        if not wait_for(lambda: health("robot", "workcell").get("watchdog") == "ok", 60):
            raise RuntimeError(f"robot did not start:\n{robot.output()[-2000:]}")
        model = load_robot("workcell")
        soft = soft_limits(model)
        center = (soft.lower + soft.upper) / 2
        # a period whose peak speed is ``speed`` of the velocity limit, within 90 % of the range
        amplitude = 0.45 * (soft.upper - soft.lower)
        period = 2 * np.pi * np.max(amplitude / (speed * soft.velocity))
        clock = [0.0]
        router.declare_subscriber("xm/clock", lambda s: clock.__setitem__(0, msgs.stamp_seconds(
            msgs.deserialize(s.payload.to_bytes(), "rosgraph_msgs/msg/Clock").clock)))
        pub = router.declare_publisher("xm/trajopt/main/trajectory")
        stop = threading.Event()

        def source() -> None:
            while not stop.is_set():
                pub.put(msgs.serialize(trajectory(model.joint_names, clock[0], center, amplitude, period)))
                time.sleep(1.0 / RATE_HZ)

        thread = threading.Thread(target=source, daemon=True)
        thread.start()
        time.sleep(5.0)  # onto the sweep (the way there from the home pose is clamped, rightly)
        hogs = start_load(load)
        before_r, before_w = health("robot", "workcell"), health("world", "sim")
        t0 = time.monotonic()
        time.sleep(seconds)
        after_r, after_w = health("robot", "workcell"), health("world", "sim")
        minutes = (time.monotonic() - t0) / 60
        stop.set()
        thread.join(2)
        board = lambda h: h["devices"]["robot"]  # noqa: E731
        err = lambda h, k: h["errors"].get(k, 0)  # noqa: E731
        brakes = board(after_w)["watchdog_brakes"] - board(before_w)["watchdog_brakes"]
        after_seq = board(after_w)["brakes_after"][-brakes:] if brakes else []
        host_gaps = set(after_r["command_stream"]["gaps_after"])
        spurious = [q for q in after_seq if q not in host_gaps]
        stop_brake = stop_and_brake(robot, lambda: health("world", "sim"))
        return {
            "load_processes": load, "seconds": seconds, "peak_speed_of_limit": speed, "stream": stream,
            "watchdog_brakes_per_min": brakes / minutes,
            "spurious_brakes_per_min": len(spurious) / minutes, "spurious_brakes_after": spurious,
            "host_gaps_braking_per_min": (after_r["command_stream"]["gaps_over_watchdog"]
                                          - before_r["command_stream"]["gaps_over_watchdog"]) / minutes,
            "host_gaps_bridged_per_min": (after_r["command_stream"]["gaps_bridged"]
                                          - before_r["command_stream"]["gaps_bridged"]) / minutes,
            "stop_brake": stop_brake,
            # trajectory time snapped to a clock that jumped (a world stalled for over 0.5 s, then caught
            # up): the setpoint jumps with it, and the host rightly clamps the chase to the velocity limit
            "command_clock_jumps": after_r["command_clock_jumps"] - before_r["command_clock_jumps"],
            "limit_brakes_per_min": (board(after_w)["limit_brakes"] - board(before_w)["limit_brakes"]) / minutes,
            "clamped_velocity_limit_per_min": (err(after_r, "clamped_velocity_limit")
                                               - err(before_r, "clamped_velocity_limit")) / minutes,
            "clamped_position_limit_per_min": (err(after_r, "clamped_position_limit")
                                               - err(before_r, "clamped_position_limit")) / minutes,
            "command_stream": after_r["command_stream"], "world_realtime_ratio": after_w.get("realtime_ratio"),
            "loadavg_1min_end": os.getloadavg()[0],
        }
    finally:
        stop_load(hogs)
        if robot is not None:
            robot.stop()
        world.stop()
        router.close()


def stop_and_brake(robot: ServiceProcess, world_health) -> dict:
    """Suspends the robot process (its command stream stops mid-stream) until the board reports a
    new watchdog brake; board times from the end of what the host sent (the last plan's last knot,
    or the last single command) and from the last frame to the brake."""
    before = world_health()["devices"]["robot"]["watchdog_brakes"]
    os.killpg(robot.proc.pid, signal.SIGSTOP)
    try:
        dev = wait_for(lambda: (lambda d: d if d["watchdog_brakes"] > before else None)(
            world_health()["devices"]["robot"]), 10, 0.05)
    finally:
        os.killpg(robot.proc.pid, signal.SIGCONT)
    if not dev:
        return {"braked": False}
    b = dev["last_brake"]
    end = b["plan_end"] if b.get("plan_end") is not None else b["last_command_at"]
    return {"braked": True, "after_commanded_end_ms": (b["at"] - end) * 1e3,
            "after_last_frame_ms": (b["at"] - b["last_command_at"]) * 1e3,
            "limit_ms": (WATCHDOG_TIMEOUT_S + PHYSICS_DT) * 1e3}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0, help="measured seconds per run (default %(default)s)")
    parser.add_argument("--load", type=int, default=os.cpu_count() or 1, metavar="N",
                        help="CPU-bound processes beside the loaded run (default: one per core, %(default)s)")
    parser.add_argument("--speed", type=float, default=0.8,
                        help="peak joint speed as a fraction of its velocity limit (default %(default)s)")
    args = parser.parse_args()
    res = {"cpu_count": os.cpu_count(), "loadavg_1min_start": os.getloadavg()[0]}
    runs = {"idle": (0, PLANS), "loaded": (args.load, PLANS), "loaded_single_commands": (args.load, SINGLE_COMMANDS)}
    for name, (load, stream) in runs.items():
        res[name] = run_once(args.seconds, load, args.speed, stream)
        print(f"{name}: " + line(res[name]))
    res["targets"] = {"spurious_brakes_per_min": 0, "clamped_velocity_limit_per_min": 0,
                      "stop_brake_after_commanded_end_ms_max": (WATCHDOG_TIMEOUT_S + PHYSICS_DT) * 1e3}
    Path(".bench").mkdir(exist_ok=True)
    Path(".bench/robot.json").write_text(json.dumps(res, indent=2))


def line(r: dict) -> str:
    s = r["command_stream"]
    b = r["stop_brake"]
    return (f"{r['load_processes']} CPU hogs, {r['seconds']:.0f} s: watchdog brakes "
            f"{r['watchdog_brakes_per_min']:.1f}/min ({r['spurious_brakes_per_min']:.1f}/min spurious; the host "
            f"left {r['host_gaps_braking_per_min']:.1f} braking gaps/min, plans bridged "
            f"{r['host_gaps_bridged_per_min']:.1f} gaps over 10 ms/min), stop -> brake "
            f"{b.get('after_commanded_end_ms', float('nan')):.1f} ms after the commanded end "
            f"({b.get('after_last_frame_ms', float('nan')):.1f} after the last frame), board time,"
            f" limit brakes {r['limit_brakes_per_min']:.1f}/min, clamps "
            f"velocity {r['clamped_velocity_limit_per_min']:.1f}/min position {r['clamped_position_limit_per_min']:.1f}"
            f"/min ({r['command_clock_jumps']} trajectory-time jumps); command stream {s['priority']}, "
            f"longest gap {s['max_gap_ms']:.1f} ms, {s['late_ticks']} late "
            f"ticks; world real-time ratio {r['world_realtime_ratio']}; load avg {r['loadavg_1min_end']:.1f}")


if __name__ == "__main__":
    main()
