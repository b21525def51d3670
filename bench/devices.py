"""Device links: how soon the robot control board brakes when commands stop, and how soon a serial
link is back after its port reappears.

Brake: 100 trials against the world's simulated board through its pty (the bench is the host: a
command stream at 250 Hz for 30-70 ms, then silence); latency is board time from the last command to
the first feedback frame reporting the brake. Baseline in the same run: the same trials on the board
logic in process (BoardSim stepped at the world's physics step), no process, pty or scheduling.
Target: every brake within 10 ms + one physics step (12 ms), never before 10 ms.

Reconnect: 20 times the device's pty vanishes and comes back; the time from its return to the
SerialLink (retry every 20 ms) being connected, against a bare poller on the same event loop trying
to open the port every 20 ms, in the same trials.

Writes .bench/devices.json.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import serial

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere

from services.robot.board_sim import BoardSim  # noqa: E402
from services.world.model import PHYSICS_DT  # noqa: E402
from services.world.pty_device import PtyDevice  # noqa: E402
from shared.kinematics import load_robot  # noqa: E402
from shared.protocols import robot_board as rb  # noqa: E402
from shared.runtime import open_router  # noqa: E402
from shared.serial_link import SerialLink  # noqa: E402
from tests.conftest import BoardHost, ServiceProcess, free_endpoint, wait_for, write_deployment  # noqa: E402

TRIALS = 100
RECONNECTS = 20
RETRY_S = 0.02
STREAM_S = (0.03, 0.05, 0.07)  # command stream lengths, in turn


def command(n: int) -> rb.CommandFrame:
    return rb.CommandFrame(0, np.full(n, rb.Mode.POSITION, np.uint8), *np.zeros((5, n)))


def brake_world(tmp: Path) -> np.ndarray:
    endpoint = free_endpoint()
    router = open_router(endpoint)
    run = tmp / "run"
    dep = write_deployment(tmp / "d.toml", endpoint, {"world": {"sim": {"robot_port": str(run / "board")}}},
                           clock="sim")
    world = ServiceProcess("world", dep, "sim", tmp / "world.log")
    try:
        if not wait_for(lambda: (run / "board").exists(), 60):
            raise RuntimeError(f"the world made no board pty: {world.output()[-2000:]}")
        host = BoardHost(run / "board")
        cmd = command(len(load_robot("workcell").joint_names))
        latencies = [host.brake_trial(cmd, STREAM_S[k % len(STREAM_S)]) for k in range(TRIALS)]
        host.close()
    finally:
        world.stop()
        router.close()
    return np.array(latencies)


def brake_in_process() -> np.ndarray:
    """The same trials on BoardSim, stepped every physics step, commands every other step (250 Hz)."""
    names = load_robot("workcell").joint_names
    n = len(names)
    latencies = []
    for k in range(TRIALS):
        board = BoardSim(names)
        cmd = command(n)
        steps = int(round(STREAM_S[k % len(STREAM_S)] / PHYSICS_DT))
        t = 0.0
        for step in range(steps + int(round(0.1 / PHYSICS_DT))):
            if step < steps and step % 2 == 0:
                cmd.sequence = step
                board.receive(cmd, t)
            _, fb = board.step(t, np.zeros(n), np.zeros(n), PHYSICS_DT)
            if fb is not None and fb.watchdog_expired and fb.last_command_sequence == cmd.sequence:
                latencies.append((fb.timestamp_us - fb.last_command_us) * 1e-6)
                break
            t = round(t + PHYSICS_DT, 9)
    return np.array(latencies)


async def reconnect(tmp: Path) -> tuple[np.ndarray, np.ndarray]:
    """Seconds from the port's return to SerialLink connected, and to a bare poller on the same event
    loop (opening the port every RETRY_S) succeeding, trial by trial."""
    path = tmp / "link"
    dev = PtyDevice(path)
    link = SerialLink(str(path), lambda _b: None, retry_s=RETRY_S)
    bare_at: list[float | None] = [0.0]

    async def bare() -> None:
        while True:
            await asyncio.sleep(RETRY_S)
            if bare_at[0] is None:
                try:
                    serial.Serial(str(path), timeout=0).close()
                    bare_at[0] = time.perf_counter()
                except (serial.SerialException, OSError):
                    pass

    async def until(cond) -> None:
        deadline = time.monotonic() + 10
        while not cond():
            if time.monotonic() > deadline:
                raise RuntimeError("the serial link did not change state within 10 s")
            await asyncio.sleep(0.001)

    tasks = [asyncio.ensure_future(link.run()), asyncio.ensure_future(bare())]
    await until(lambda: link.connected)
    ours, theirs = [], []
    for _ in range(RECONNECTS):
        dev.close()
        await until(lambda: not link.connected)
        bare_at[0] = None
        dev = PtyDevice(path)
        t0 = time.perf_counter()
        await until(lambda: link.connected)
        ours.append(time.perf_counter() - t0)
        await until(lambda: bare_at[0] is not None)
        theirs.append(bare_at[0] - t0)
    link.close()
    for task in tasks:
        task.cancel()
    dev.close()
    return np.array(ours), np.array(theirs)


def summary(x: np.ndarray, scale: float = 1e3) -> dict:
    return {"n": int(len(x)), "median": float(np.median(x) * scale), "p99": float(np.percentile(x, 99) * scale),
            "max": float(x.max() * scale), "min": float(x.min() * scale)}


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    logging.getLogger("xm").setLevel(logging.ERROR)  # the link logs every loss and return
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        world = brake_world(tmp)
        local = brake_in_process()
        link, bare = asyncio.run(reconnect(tmp))
    target_ms = (0.010 + PHYSICS_DT) * 1e3
    res = {
        "brake_world_ms": summary(world), "brake_in_process_ms": summary(local),
        "brake_median_ratio_to_in_process": float(np.median(world) / np.median(local)),
        "brake_trials_within_target": int(np.sum((world > 0.010) & (world <= 0.010 + PHYSICS_DT + 1e-6))),
        "reconnect_link_ms": summary(link), "reconnect_bare_ms": summary(bare),
        "reconnect_median_ratio_to_bare": float(np.median(link) / np.median(bare)),
        "targets": {"brake_ms_max": target_ms, "brake_ms_min_exclusive": 10.0, "trials": TRIALS},
    }
    Path(".bench").mkdir(exist_ok=True)
    Path(".bench/devices.json").write_text(json.dumps(res, indent=2))
    w, b = res["brake_world_ms"], res["brake_in_process_ms"]
    print(f"brake after silence, board time: world median {w['median']:.1f} ms, max {w['max']:.1f} ms, "
          f"min {w['min']:.1f} ms ({res['brake_trials_within_target']}/{TRIALS} within (10, {target_ms:.0f}] ms); "
          f"in process median {b['median']:.1f} ms, max {b['max']:.1f} ms "
          f"({res['brake_median_ratio_to_in_process']:.2f}x)")
    lk, bb = res["reconnect_link_ms"], res["reconnect_bare_ms"]
    print(f"reconnect: SerialLink median {lk['median']:.1f} ms, p99 {lk['p99']:.1f} ms; bare loop median "
          f"{bb['median']:.1f} ms ({res['reconnect_median_ratio_to_bare']:.2f}x)")


if __name__ == "__main__":
    main()
