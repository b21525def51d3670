"""P7: the recorder at a real rig's rates.

Publishes synthetic streams through a private router for ``--seconds`` (default 60): 7 cameras at
30 fps (640x480 JPEG of ~100 kB, with their CameraInfo), 2 gloves' raw impedance frames at
1 kHz (``xm/glove/*/raw``, 16x16 complex) beside their 100 Hz tactile, robot state at 500 Hz, and
every other registered key at its nominal rate, all stamped on one clock that is published too.
``xm record`` records them as a separate process. Reports per key what was published and what the
file holds (read back with the stock ``mcap`` + ``mcap_ros2`` readers), the recorder's CPU share
of one core over the window, and writes .bench/recorder.json. Target (P7): 0 messages lost on
every key at <= 25 % of one core.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # runnable as a script from anywhere

from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

from services.recorder.writer import recording_files  # noqa: E402
from shared import keys, msgs  # noqa: E402
from shared.runtime import open_client, open_router  # noqa: E402
from tests.bad_messages import good  # noqa: E402
from tests.conftest import free_endpoint  # noqa: E402

CAMERA_HZ, RAW_HZ, STATE_HZ = 30.0, 1000.0, 500.0
CELLS = 16
CPU_TARGET = 0.25
RATE_REACHED = 0.98  # a stream whose publisher fell further behind than this was held up by the recorder


def jpeg(kb: float, seed: int) -> np.ndarray:
    """A 640x480 JPEG of about ``kb`` kB: a smooth scene with sensor noise (noise sets the size)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:480, 0:640]
    base = np.stack([x / 640 * 200, y / 480 * 200, (x + y) / 1120 * 200], -1)
    for sigma in (0.5, 1, 2, 4, 8, 16, 32):
        img = np.clip(base + rng.normal(0, sigma, base.shape), 0, 255).astype(np.uint8)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
        if len(buf) >= kb * 1024:
            break
    return buf.ravel()


def streams(jpeg_kb: float) -> list[tuple[str, str, float, object]]:
    """(key, type, rate, make(t) -> message) per stream."""
    out = []
    for spec in keys.REGISTRY:
        rate = spec.rate_hz
        if "/camhub/" in spec.key:
            rate = CAMERA_HZ
        elif spec.key.endswith("/state") and "/robot/" in spec.key:
            rate = STATE_HZ
        out.append((spec.key, spec.msgtype, rate, lambda t, m=spec.msgtype: good(m, t)))
    images = {spec.key: jpeg(jpeg_kb, i) for i, spec in enumerate(keys.REGISTRY) if spec.key.endswith("/image")}
    for i, (key, typ, rate, _) in enumerate(out):
        if key in images:
            out[i] = (key, typ, rate, lambda t, k=key: msgs.make(
                "sensor_msgs/msg/CompressedImage", header=msgs.header(t, k), format="jpeg", data=images[k]))
    for hand in keys.GLOVES:
        out.append((f"xm/glove/{hand}/raw", "xm_msgs/msg/TactileRaw", RAW_HZ, lambda t, h=hand: msgs.make(
            "xm_msgs/msg/TactileRaw", header=msgs.header(t, h), hand=h, rows=CELLS, cols=CELLS,
            real=np.ones(CELLS * CELLS, np.float32), imag=np.zeros(CELLS * CELLS, np.float32), sequence=0)))
    return out


def publish(pub, key: str, msgtype: str, rate: float, make, t0: float, seconds: float,
            sent: Counter, stop: threading.Event) -> None:
    """Puts one stream on its own schedule; a late thread sends what is due, never a burst."""
    n = 0
    while not stop.is_set():
        due = t0 + n / rate
        now = time.monotonic()
        if due > t0 + seconds:
            break
        if due > now:
            time.sleep(due - now)
        pub.put(msgs.serialize(make(time.time()), msgtype))
        sent[key] += 1
        n = max(n + 1, int((time.monotonic() - t0) * rate))  # skip what a stall made late


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def recorded(path: Path) -> tuple[Counter, int]:
    """Messages per key in the recording's segments, decoded with the stock readers; and how many
    failed to decode."""
    counts: Counter = Counter()
    failed = 0
    for f in recording_files(path):
        with f.open("rb") as fh:
            for _schema, channel, _message, decoded in make_reader(
                    fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
                counts[channel.topic] += 1
                failed += decoded is None
    return counts, failed


def run(seconds: float, jpeg_kb: float) -> dict:
    endpoint = free_endpoint()
    router = open_router(endpoint)
    tmp = Path(tempfile.mkdtemp(prefix="bench-recorder-"))
    out = tmp / "rig.mcap"
    rec = subprocess.Popen([sys.executable, "-m", "shared.cli", "record", "--router", endpoint, "-o", str(out),
                            "--keys", "xm/**"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True)
    session = open_client(endpoint)
    try:
        time.sleep(5.0)  # the recorder subscribes (its imports take a few seconds)
        plan = streams(jpeg_kb)
        sent: Counter = Counter()
        stop = threading.Event()
        # declared well ahead: a publisher drops what it puts before it has heard of the recorder; and
        # blocking rather than dropping when the transport is full, so a loss is the recorder's and
        # a recorder that cannot keep up shows as rates the publishers did not reach
        pubs = [session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
                for k, _m, _r, _f in plan]
        t0 = time.monotonic() + 2.0
        threads = [threading.Thread(target=publish, args=(p, k, m, r, f, t0, seconds, sent, stop), daemon=True)
                   for p, (k, m, r, f) in zip(pubs, plan, strict=True)]
        cpu0 = cpu_seconds(rec.pid)
        for th in threads:
            th.start()
        for th in threads:
            th.join(seconds + 30)
        cpu = (cpu_seconds(rec.pid) - cpu0) / seconds
        time.sleep(2.0)  # the last messages reach the recorder
        rec.send_signal(signal.SIGINT)
        log = rec.communicate(timeout=60)[0]
    finally:
        if rec.poll() is None:
            rec.kill()
        session.close()
        router.close()
    counts, failed = recorded(out)
    per_key = {k: {"rate_hz": r, "published": sent[k], "reached_rate": round(sent[k] / (seconds * r), 3),
                   "recorded": counts[k], "lost": sent[k] - counts[k]} for k, _m, r, _f in plan}
    return {"seconds": seconds, "jpeg_bytes": int(len(jpeg(jpeg_kb, 0))), "keys": per_key,
            "published": sum(sent.values()), "recorded": sum(counts[k] for k in per_key),
            "lost": sum(max(0, v["lost"]) for v in per_key.values()), "undecodable": failed,
            "recorder_cpu_share_of_one_core": round(cpu, 3), "recorder_exit": rec.returncode,
            "recorder_log_tail": log[-1500:], "loadavg_1m": os.getloadavg()[0]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0, help="publishing time (default %(default)s)")
    parser.add_argument("--jpeg-kb", type=float, default=90.0, help="size of each camera frame (default %(default)s)")
    args = parser.parse_args()
    res = run(args.seconds, args.jpeg_kb)
    res["targets"] = {"lost": 0, "recorder_cpu_share_of_one_core_max": CPU_TARGET, "min_reached_rate": RATE_REACHED}
    res["min_reached_rate"] = min(v["reached_rate"] for v in res["keys"].values())
    res["met"] = (res["lost"] == 0 and res["undecodable"] == 0 and res["min_reached_rate"] >= RATE_REACHED
                  and res["recorder_cpu_share_of_one_core"] <= CPU_TARGET)
    Path(ROOT / ".bench").mkdir(exist_ok=True)
    (ROOT / ".bench/recorder.json").write_text(json.dumps(res, indent=2))
    for k, v in res["keys"].items():
        print(f"{k:32} {v['rate_hz']:7.0f} Hz  published {v['published']:6d} ({v['reached_rate']:.0%} of the "
              f"rate)  recorded {v['recorded']:6d}  lost {v['lost']}")
    print(f"{res['published']} published, {res['recorded']} recorded, {res['lost']} lost, {res['undecodable']} "
          f"undecodable; slowest stream at {res['min_reached_rate']:.0%} of its rate;"
          f" recorder CPU {res['recorder_cpu_share_of_one_core']:.0%} of one core (target <= 25 %); "
          f"load {res['loadavg_1m']:.1f}")


if __name__ == "__main__":
    main()
