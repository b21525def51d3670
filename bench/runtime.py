"""P1: the typed runtime against raw zenoh-python in the same run.

Ping-pong latency (64 B payload, p50/p99) and one-way throughput of 4 kB and 300 kB messages
(a camera frame, as a CompressedImage), through a router on loopback as in a deployment, every session opened alike
(shared/runtime/zsession.py). Throughput publishers block when the transport is congested (raw
and typed alike), so both count delivered capacity rather than what a flood left after drops.
The typed runtime is measured both ways a subscription can run: handlers on the event loop (the
default) and ``inline`` on Zenoh's threads (shared/runtime/node.py). At 300 kB the typed
publisher puts from its shared-memory pool (shared/runtime/shm.py); the raw baseline is measured
both as plain bytes and copying each payload into a pool buffer of the same size first
(zenoh-python's own way), and the ratio is taken against the faster. Throughput runs ``--repeat``
times interleaved; medians of rates and of per-round ratios are reported, with the process's CPU
time per message and the host's load. ``--rss-seconds`` adds a long run in separate processes
(router, publisher of 300 kB images, subscriber) sampling each one's RSS, then restarts the
publisher to measure what each restart leaves mapped. Writes .bench/runtime.json; targets:
latency <= 1.15x raw, throughput >= 0.8x raw.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh
from zenoh.shm import GarbageCollect, ShmProvider

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere

from bench import _shm_rss as shm_rss  # noqa: E402
from shared import msgs  # noqa: E402
from shared.runtime import Node, fifo, latest, open_client, open_router, shm  # noqa: E402

N_PING = 2000
N_WARM = 200
N_THROUGHPUT = 100_000  # about a second at 4 kB: a shorter run is mostly scheduling noise
N_THROUGHPUT_LARGE = 5000
SIZES = (4096, 300_000)  # a 4 kB message, a camera frame
PING_TYPE = "std_msgs/msg/String"
BULK_TYPE = "std_msgs/msg/UInt8MultiArray"  # a generic payload (4 kB)
IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"  # a camera frame (300 kB): the pool carries sensor types only
IMAGE_BYTES = 64 * 1024  # from this size the bulk runs send camera frames
STALL_S = 0.2  # a throughput run ends early when nothing arrived for this long


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def raw_pingpong(endpoint: str) -> np.ndarray:
    a, b = open_client(endpoint), open_client(endpoint)
    pong_pub = b.declare_publisher("bench/raw/pong")
    b.declare_subscriber("bench/raw/ping", lambda s: pong_pub.put(s.payload))
    got = threading.Event()
    a.declare_subscriber("bench/raw/pong", lambda s: got.set())
    ping = a.declare_publisher("bench/raw/ping")
    time.sleep(0.5)
    payload = b"x" * 64
    rtts = []
    for i in range(N_PING + N_WARM):
        got.clear()
        t0 = time.perf_counter()
        ping.put(payload)
        got.wait(10.0)
        if i >= N_WARM:
            rtts.append(time.perf_counter() - t0)
    a.close()
    b.close()
    return np.array(rtts)


def raw_throughput(endpoint: str, size: int, from_pool: bool = False) -> tuple[float, float]:
    """Raw puts of ``size`` bytes. ``from_pool``: each payload copied into a buffer of a
    shared-memory pool of the typed runtime's size and put from there (as bytes when the pool is
    full), zenoh-python's own way for a large payload to a process on the same host."""
    a, b = open_client(endpoint), open_client(endpoint)
    arrivals = Arrivals(n_for(size))
    n = arrivals.n
    b.declare_subscriber("bench/raw/bulk", arrivals)
    pub = a.declare_publisher("bench/raw/bulk", congestion_control=zenoh.CongestionControl.BLOCK)
    provider = ShmProvider.default_backend(shm.POOL_BYTES) if from_pool else None
    time.sleep(0.5)
    payload = b"y" * size
    copied = 0
    arrivals.start()
    for _ in range(n):
        if provider is None:
            pub.put(payload)
            continue
        try:
            buf = provider.alloc(size, policy=GarbageCollect())
        except zenoh.ZError:
            pub.put(payload)
            copied += 1
            continue
        buf[0:size] = payload
        pub.put(buf)
    while arrivals.waiting():
        time.sleep(STALL_S)
    a.close()
    b.close()
    print(f"raw throughput {size} B{' from a shared-memory pool' if from_pool else ''}: {arrivals.count}/{n} received"
          + (f", {copied} copied (pool full)" if from_pool else ""))
    return arrivals.result()


def n_for(size: int) -> int:
    return N_THROUGHPUT if size <= 4096 else N_THROUGHPUT_LARGE


class Arrivals:
    """The receiving handler of a throughput run, raw and typed alike: counts deliveries (one thread
    at a time calls it: a subscriber's callback thread, or the loop) and notes the time and the
    process's CPU time at the last one, so the run ends when the last message arrives, not when a
    waiter next looks."""

    def __init__(self, n: int) -> None:
        self.n, self.count = n, 0
        self.t0 = self.cpu0 = self.t_end = self.cpu_end = self.t_seen = self.cpu_seen = 0.0
        self._seen = -1

    def __call__(self, *_args: object) -> None:
        self.count += 1
        if self.count == self.n:
            self.t_end, self.cpu_end = time.perf_counter(), time.process_time()

    def start(self) -> None:
        self.t0, self.cpu0 = time.perf_counter(), time.process_time()

    def waiting(self) -> bool:
        """Whether to look again after STALL_S: not all arrived, and some arrived since the last look
        (a stalled run ends at its last look that saw progress)."""
        if self.count >= self.n:
            return False
        if self.count == self._seen:
            return False
        self._seen, self.t_seen, self.cpu_seen = self.count, time.perf_counter(), time.process_time()
        return True

    def result(self) -> tuple[float, float]:
        """(messages per second, process CPU microseconds per message)"""
        t, cpu = (self.t_end, self.cpu_end) if self.count >= self.n else (self.t_seen, self.cpu_seen)
        return self.count / (t - self.t0), (cpu - self.cpu0) / max(self.count, 1) * 1e6


async def typed_pingpong(endpoint: str, inline: bool) -> np.ndarray:
    """Round trips through two typed nodes: handlers on the event loop, or ``inline`` on Zenoh's threads."""
    a = Node("bench", "ping", open_client(endpoint))
    b = Node("bench", "pong", open_client(endpoint))
    pong_pub = b.publisher("xm/bench/pong/out", PING_TYPE)
    b.subscribe("xm/bench/ping/out", pong_pub.put, latest(1), msgtype=PING_TYPE, inline=inline)
    got = threading.Event()
    waiter: list[asyncio.Future] = []
    loop = asyncio.get_running_loop()
    a.subscribe("xm/bench/pong/out", (lambda _m: got.set()) if inline else lambda m: waiter[0].set_result(m), latest(1),
                msgtype=PING_TYPE, inline=inline)
    ping = a.publisher("xm/bench/ping/out", PING_TYPE)
    await asyncio.sleep(0.5)
    msg = msgs.make(PING_TYPE, data="x" * 56)  # 64 B on the wire with CDR header and length

    def inline_rounds() -> list[float]:
        out = []
        for i in range(N_PING + N_WARM):
            got.clear()
            t0 = time.perf_counter()
            ping.put(msg)
            got.wait(10.0)
            if i >= N_WARM:
                out.append(time.perf_counter() - t0)
        return out

    if inline:
        rtts = await asyncio.to_thread(inline_rounds)
    else:
        rtts = []
        for i in range(N_PING + N_WARM):
            waiter[:] = [loop.create_future()]
            t0 = time.perf_counter()
            ping.put(msg)
            with contextlib.suppress(asyncio.TimeoutError):  # a stalled round counts at 10 s, as raw's does
                await asyncio.wait_for(waiter[0], 10.0)
            if i >= N_WARM:
                rtts.append(time.perf_counter() - t0)
    for node in (a, b):
        await node.close()
        node.session.close()
    return np.array(rtts)


async def typed_throughput(endpoint: str, size: int, inline: bool) -> tuple[float, float]:
    a = Node("bench", "src", open_client(endpoint))
    b = Node("bench", "dst", open_client(endpoint))
    arrivals = Arrivals(n_for(size))
    msgtype = IMAGE_TYPE if size >= IMAGE_BYTES else BULK_TYPE
    b.subscribe("xm/bench/src/bulk", arrivals, fifo(), msgtype=msgtype, inline=inline)
    pub = a.publisher("xm/bench/src/bulk", msgtype, block=True)
    await asyncio.sleep(0.5)
    msg = bulk_message(size)
    arrivals.start()
    for i in range(arrivals.n):
        pub.put(msg)
        if i % 500 == 0:
            await asyncio.sleep(0)  # let the receiving side run, as a service loop would
    while arrivals.waiting():
        await asyncio.sleep(STALL_S)
    print(f"typed{' inline' if inline else ''} throughput {size} B: {arrivals.count}/{arrivals.n} received, "
          f"{pub.shm_sent} from the shared-memory pool, errors {dict(a.stats.errors) | dict(b.stats.errors)}")
    for node in (a, b):
        await node.close()
        node.session.close()
    return arrivals.result()


def bulk_message(size: int) -> object:
    """``size`` bytes on the wire: a byte array, or from IMAGE_BYTES on a JPEG-typed CompressedImage."""
    if size < IMAGE_BYTES:
        layout = msgs.make("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0)
        return msgs.make(BULK_TYPE, layout=layout, data=np.full(size - 16, 7, np.uint8))

    def image(n: int) -> object:
        return msgs.make(IMAGE_TYPE, header=msgs.header(time.time(), "cam0"), format="jpeg",
                         data=np.full(n, 7, np.uint8))
    return image(size - msgs.pieces_writer(IMAGE_TYPE)(image(0))[1])


def percentiles(lat: np.ndarray) -> dict:
    return {"p50_us": float(np.percentile(lat, 50) * 1e6), "p99_us": float(np.percentile(lat, 99) * 1e6)}


def throughput_rounds(endpoint: str, repeat: int) -> dict:
    """Every path at every size, ``repeat`` rounds interleaved: per size and path the rates and CPU
    per message of each round, their medians, and the medians of each round's typed/raw ratios."""
    rounds: dict[str, dict[str, list]] = {str(size): {} for size in SIZES}
    for _ in range(repeat):
        for size in SIZES:
            runs = {"raw": raw_throughput(endpoint, size)}
            if size >= shm.MIN_BYTES:
                runs["raw_pool"] = raw_throughput(endpoint, size, from_pool=True)
            runs["loop"] = asyncio.run(typed_throughput(endpoint, size, False))
            runs["inline"] = asyncio.run(typed_throughput(endpoint, size, True))
            for path, (rate, cpu) in runs.items():
                rounds[str(size)].setdefault(path, []).append({"msg_s": rate, "cpu_us_per_msg": cpu})
    out: dict = {}
    for size, paths in rounds.items():
        base = [max(r["msg_s"], p["msg_s"]) for r, p in zip(paths["raw"], paths.get("raw_pool", paths["raw"]),
                                                              strict=True)]
        out[size] = {
            "rounds": paths,
            "median_msg_s": {k: float(np.median([r["msg_s"] for r in v])) for k, v in paths.items()},
            "median_cpu_us_per_msg": {k: float(np.median([r["cpu_us_per_msg"] for r in v])) for k, v in paths.items()},
            "median_ratio": {k: float(np.median([r["msg_s"] / b for r, b in zip(paths[k], base, strict=True)]))
                             for k in ("loop", "inline")},
            "baseline": "raw_pool" if "raw_pool" in paths else "raw",
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=5, help="throughput rounds (default %(default)s)")
    parser.add_argument("--rss-seconds", type=float, default=0.0,
                        help="also stream 300 kB images between processes this long, sampling RSS (default: no)")
    parser.add_argument("--restarts", type=int, default=5,
                        help="publisher restarts after the RSS run (default %(default)s)")
    args = parser.parse_args()
    load_before = os.getloadavg()[0]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    raw = [raw_pingpong(endpoint)]
    lat = {"loop": asyncio.run(typed_pingpong(endpoint, False)), "inline": asyncio.run(typed_pingpong(endpoint, True))}
    raw.append(raw_pingpong(endpoint))  # again, so drift of the machine shows up
    lat["raw"] = np.concatenate(raw)
    tp = throughput_rounds(endpoint, args.repeat)
    router.close()
    res: dict = {"latency_us": {k: percentiles(v) for k, v in lat.items()}, "throughput": tp,
                 "loadavg_1m": {"start": load_before, "end": os.getloadavg()[0]}, "cpus": os.cpu_count()}
    res["ratios"] = {path: {
        "latency_p50": res["latency_us"][path]["p50_us"] / res["latency_us"]["raw"]["p50_us"],
        "latency_p99": res["latency_us"][path]["p99_us"] / res["latency_us"]["raw"]["p99_us"],
        **{f"throughput_{size}": tp[str(size)]["median_ratio"][path] for size in SIZES}}
        for path in ("loop", "inline")}
    res["targets"] = {"latency_ratio_max": 1.15, "throughput_ratio_min": 0.8}
    if args.rss_seconds > 0:
        res["shm_rss"] = shm_rss.measure(args.rss_seconds, args.restarts)
    Path(".bench").mkdir(exist_ok=True)
    Path(".bench/runtime.json").write_text(json.dumps(res, indent=2))
    print(f"{'':>8}{'p50 us':>10}{'p99 us':>10}")
    for path in ("raw", "loop", "inline"):
        print(f"{path:>8}{res['latency_us'][path]['p50_us']:>10.0f}{res['latency_us'][path]['p99_us']:>10.0f}")
    for size in SIZES:
        t = tp[str(size)]
        cpu = t["median_cpu_us_per_msg"]
        print(f"{size} B, median of {args.repeat}: " + ", ".join(
            f"{k} {v:.0f} msg/s ({cpu[k]:.1f} us CPU/msg)" for k, v in t["median_msg_s"].items()))
    for path, r in res["ratios"].items():
        print(f"{path} / raw: " + ", ".join(f"{k} {v:.2f}x" for k, v in r.items())
              + " (targets: latency <= 1.15x, throughput >= 0.8x)")
    print(f"load average {load_before:.1f} at the start, {res['loadavg_1m']['end']:.1f} at the end, "
          f"{os.cpu_count()} CPUs")
    if "shm_rss" in res:
        shm_rss.report(res["shm_rss"])


if __name__ == "__main__":
    main()
