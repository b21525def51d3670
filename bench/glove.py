"""P2: two gloves at 1 kHz each, pty bytes to published Zenoh message, through the real glove
service processes. Reports loss, latency p50/p99 (send -> subscriber callback) and the glove
processes' CPU share, next to the raw pty transfer latency measured in the same run.

Runs twice: on the host as it is ("idle": other jobs on the machine are not stopped, so say what
else ran), then with ``--load N`` CPU-bound processes beside it (default: one per core), and
writes both to .bench/glove.json with the load average seen. Where frames go missing is reported
too: bytes the simulated device had to drop (its FIFO overflowed) and its FIFO's peak fill.
Targets: idle 0 lost, p99 <= 2 ms; loaded 0 lost, p99 <= 5 ms."""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil
import serial

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere

from services.glove.sensor_model import GloveSensorModel  # noqa: E402
from services.world.pty_device import PtyDevice  # noqa: E402
from shared import msgs  # noqa: E402
from shared.protocols import tactile  # noqa: E402
from shared.runtime import open_client, open_router  # noqa: E402
from tests.conftest import free_port, write_deployment  # noqa: E402

RATE_HZ = 1000
SECONDS = 5.0
HANDS = ("left", "right")


def raw_pty_latency(n: int = 2000) -> np.ndarray:
    """Baseline: the same bytes through a pty to a plain blocking reader, in a process of its own at
    SCHED_FIFO where permitted (as the glove readers), under the same load as the glove run."""
    parent, child = multiprocessing.get_context("fork").Pipe()
    proc = multiprocessing.get_context("fork").Process(target=_raw_pty_latency, args=(n, child))
    proc.start()
    out = parent.recv()
    proc.join(5)
    return out


def _raw_pty_latency(n: int, conn) -> None:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
    except (OSError, AttributeError):
        pass

    with tempfile.TemporaryDirectory() as tmp:
        dev = PtyDevice(Path(tmp) / "raw")
        ser = serial.Serial(str(Path(tmp) / "raw"), timeout=1)
        frame = tactile.encode_frame(tactile.TactileFrame(0, 0, np.zeros((16, 16), np.complex64)))
        out = []
        for _ in range(n):
            t0 = time.perf_counter()
            dev.write(frame)
            ser.read(len(frame))
            out.append(time.perf_counter() - t0)
            time.sleep(0.001)
        ser.close()
        dev.close()
    conn.send(np.array(out))


def start_load(n: int) -> list[subprocess.Popen]:
    """``n`` CPU-bound processes at normal priority, spinning until killed."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True,
                             preexec_fn=normal_priority) for _ in range(n)]


def stop_load(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
        p.wait(5)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--load", type=int, default=os.cpu_count() or 1, metavar="N",
                        help="CPU-bound processes beside the loaded run (default: one per core, %(default)s)")
    args = parser.parse_args()
    if args.load < 0:
        parser.error("--load must be >= 0")
    res = {"load_processes": args.load, "cpu_count": os.cpu_count(), "harness_priority": harness_priority(),
           "idle": run_once(0)}
    print("idle:   " + line(res["idle"]))
    res["loaded"] = run_once(args.load)
    print(f"loaded: {line(res['loaded'])}")
    res["targets"] = {"idle": {"lost": 0, "latency_p99_ms_max": 2.0}, "loaded": {"lost": 0, "latency_p99_ms_max": 5.0}}
    res["loaded_p99_ratio_to_idle"] = res["loaded"]["latency_p99_ms"] / max(res["idle"]["latency_p99_ms"], 1e-9)
    Path(".bench").mkdir(exist_ok=True)
    Path(".bench/glove.json").write_text(json.dumps(res, indent=2))


HARNESS_NICE = -10


def harness_priority() -> str:
    """The bench's own router, subscriber and frame sender stand in for the workcell's consumers and
    the device: run them at nice -10 (threads created later inherit it; the glove services and the
    hogs are started back at nice 0) so that the figures measure the glove service rather than a
    harness starved by the hogs. Not real-time: the subscriber decodes 2000 messages/s in Python,
    and real-time threads using most of a CPU are throttled by the kernel, stalling every real-time
    thread on that CPU (the glove readers among them)."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, HARNESS_NICE)
        return f"nice {HARNESS_NICE}"
    except OSError as exc:
        print(f"warning: bench harness at normal priority ({exc}): its own delays count as latency", file=sys.stderr)
        return "normal"


def normal_priority() -> None:
    """For the processes the bench starts: back to nice 0."""
    os.setpriority(os.PRIO_PROCESS, 0, 0)


def line(r: dict) -> str:
    return (f"2 gloves x {RATE_HZ} Hz for {SECONDS:.0f} s with {r['load_processes']} CPU hogs (load avg "
            f"{r['loadavg_1min_before']:.1f}): lost {r['lost']}/{r['sent']}, latency p50 {r['latency_p50_ms']:.2f} ms, "
            f"p99 {r['latency_p99_ms']:.2f} ms (raw pty p50 {r['raw_pty_p50_ms']:.3f} ms, "
            f"p99 {r['raw_pty_p99_ms']:.2f} ms, max {r['raw_pty_max_ms']:.1f} ms); device dropped "
            f"{r['device_dropped_bytes']} B, FIFO peak {r['device_fifo_peak_bytes']} B; CPU per glove process "
            + ", ".join(f"{h} {v:.0%}" for h, v in r["cpu_share_per_glove_process"].items()))


def run_once(load: int) -> dict:
    loadavg = os.getloadavg()[0]
    hogs = start_load(load)
    try:
        return {"load_processes": load, "loadavg_1min_before": loadavg, **measure()}
    finally:
        stop_load(hogs)


def send_frames(devices: dict[str, PtyDevice], frames: dict[str, list[bytes]], conn) -> None:
    """The two readout modules: a process of its own (no GIL shared with the bench's subscriber),
    SCHED_FIFO where permitted, writing each glove's frame every millisecond; sends back the write
    times, the elapsed time and each device's (dropped bytes, FIFO peak). It sleeps, never spins: a
    real-time thread that spins runs into the kernel's real-time throttling."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(20))
    except (OSError, AttributeError):
        pass
    n = len(frames[HANDS[0]])
    sent = {h: np.zeros(n) for h in HANDS}
    t0 = time.perf_counter()
    for i in range(n):
        time.sleep(max(0.0, t0 + i / RATE_HZ - time.perf_counter()))
        for h in HANDS:
            sent[h][i] = time.perf_counter()
            devices[h].write(frames[h][i])
    elapsed = time.perf_counter() - t0
    deadline = time.perf_counter() + 1.0
    while any(d.backlog for d in devices.values()) and time.perf_counter() < deadline:
        for d in devices.values():
            d.flush()
        time.sleep(0.001)
    conn.send((sent, elapsed, {h: (d.dropped_bytes, d.fifo_peak) for h, d in devices.items()}))


def measure() -> dict:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    tmp = Path(tempfile.mkdtemp())
    devices = {h: PtyDevice(tmp / f"glove-{h}") for h in HANDS}
    dep = write_deployment(tmp / "bench.toml", endpoint, {"glove": {h: {"port": str(tmp / f"glove-{h}")}
                                                                    for h in HANDS}})
    procs = {h: subprocess.Popen([sys.executable, "-m", "services.glove", "--deployment", str(dep), "--instance", h],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                                 preexec_fn=normal_priority)
             for h in HANDS}
    session = open_client(endpoint)
    n = int(RATE_HZ * SECONDS)
    received: dict[str, dict[int, float]] = {h: {} for h in HANDS}
    lock = threading.Lock()

    def on(sample) -> None:
        t = time.perf_counter()
        m = msgs.deserialize(sample.payload.to_bytes(), "xm_msgs/msg/Tactile")
        with lock:
            received[m.hand][m.sequence] = t

    session.declare_subscriber("xm/glove/*/tactile", on)
    model = GloveSensorModel(0)
    frames = {h: [tactile.encode_frame(tactile.TactileFrame(i, i * 1000, model.impedance(np.ones(6), i * 1e-3)))
                  for i in range(n)] for h in HANDS}
    time.sleep(3.0)  # services up and connected
    warm = {h: tactile.encode_frame(tactile.TactileFrame(10**6, 0, np.zeros((16, 16), np.complex64))) for h in HANDS}
    for h in HANDS:
        devices[h].write(warm[h])
    time.sleep(0.5)
    cpu = {h: psutil.Process(p.pid) for h, p in procs.items()}
    for c in cpu.values():
        c.cpu_percent(None)
    parent, child = multiprocessing.get_context("fork").Pipe()
    sender = multiprocessing.get_context("fork").Process(target=send_frames, args=(devices, frames, child))
    sender.start()
    sent, elapsed, fifo = parent.recv()
    sender.join(5)
    time.sleep(1.0)
    cpu_share = {h: c.cpu_percent(None) / 100.0 for h, c in cpu.items()}
    for p in procs.values():
        os.killpg(p.pid, signal.SIGTERM)
        p.wait(5)
    session.close()
    router.close()
    lat, lost = [], 0
    for h in HANDS:
        got = received[h]
        lost += sum(1 for i in range(n) if i not in got)
        lat += [got[i] - sent[h][i] for i in range(n) if i in got]
    lat = np.array(lat) if lat else np.array([np.nan])
    raw = raw_pty_latency()
    dropped, peak = sum(f[0] for f in fifo.values()), max(f[1] for f in fifo.values())
    for d in devices.values():
        d.close()
    res = {"gloves": len(HANDS), "rate_hz": RATE_HZ, "seconds": SECONDS, "send_rate_achieved_hz": n / elapsed,
           "sent": n * len(HANDS), "lost": lost, "latency_p50_ms": float(np.percentile(lat, 50) * 1e3),
           "latency_p99_ms": float(np.percentile(lat, 99) * 1e3), "latency_max_ms": float(np.max(lat) * 1e3),
           "raw_pty_p50_ms": float(np.median(raw) * 1e3), "raw_pty_p99_ms": float(np.percentile(raw, 99) * 1e3),
           "raw_pty_max_ms": float(raw.max() * 1e3), "device_dropped_bytes": dropped,
           "device_fifo_peak_bytes": peak, "cpu_share_per_glove_process": cpu_share}
    res["latency_p50_ratio_to_raw_pty"] = res["latency_p50_ms"] / res["raw_pty_p50_ms"]
    res["latency_p99_ratio_to_raw_pty"] = res["latency_p99_ms"] / res["raw_pty_p99_ms"]
    return res


if __name__ == "__main__":
    main()
