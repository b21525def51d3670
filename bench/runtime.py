"""P1: the typed runtime against raw zenoh-python in the same run.

Ping-pong latency (64 B payload, p50/p99) and one-way 4 KB throughput, both through a router on
loopback as in a deployment. Writes .bench/runtime.json; targets: latency <= 1.15x raw,
throughput >= 0.8x raw.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere

from shared import msgs  # noqa: E402
from shared.runtime import Node, fifo, latest, open_client, open_router  # noqa: E402

N_PING = 2000
N_WARM = 200
N_THROUGHPUT = 20000
PING_TYPE = "std_msgs/msg/String"
BULK_TYPE = "std_msgs/msg/UInt8MultiArray"


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
        got.wait(2.0)
        if i >= N_WARM:
            rtts.append(time.perf_counter() - t0)
    a.close()
    b.close()
    return np.array(rtts)


def raw_throughput(endpoint: str) -> float:
    a, b = open_client(endpoint), open_client(endpoint)
    count = [0]
    done = threading.Event()

    def on(_s) -> None:
        count[0] += 1
        if count[0] == N_THROUGHPUT:
            done.set()

    b.declare_subscriber("bench/raw/bulk", on)
    pub = a.declare_publisher("bench/raw/bulk")
    time.sleep(0.5)
    payload = b"y" * 4096
    t0 = time.perf_counter()
    for _ in range(N_THROUGHPUT):
        pub.put(payload)
    last, t_last = -1, time.perf_counter()
    while not done.is_set() and count[0] != last:  # stop when everything arrived or nothing more comes
        last, t_last = count[0], time.perf_counter()
        done.wait(0.2)
    elapsed = (time.perf_counter() if done.is_set() else t_last) - t0
    a.close()
    b.close()
    print(f"raw throughput: {count[0]}/{N_THROUGHPUT} received")
    return count[0] / elapsed


async def typed_pingpong(endpoint: str) -> np.ndarray:
    a = Node("bench", "ping", open_client(endpoint))
    b = Node("bench", "pong", open_client(endpoint))
    pong_pub = b.publisher("xm/bench/pong/out", PING_TYPE)
    b.subscribe("xm/bench/ping/out", pong_pub.put, latest(1), msgtype=PING_TYPE)
    waiter: list[asyncio.Future] = []
    a.subscribe("xm/bench/pong/out", lambda m: waiter[0].set_result(m), latest(1), msgtype=PING_TYPE)
    ping = a.publisher("xm/bench/ping/out", PING_TYPE)
    await asyncio.sleep(0.5)
    msg = msgs.make(PING_TYPE, data="x" * 56)  # 64 B on the wire with CDR header and length
    loop = asyncio.get_running_loop()
    rtts = []
    for i in range(N_PING + N_WARM):
        waiter[:] = [loop.create_future()]
        t0 = time.perf_counter()
        ping.put(msg)
        await asyncio.wait_for(waiter[0], 2.0)
        if i >= N_WARM:
            rtts.append(time.perf_counter() - t0)
    for node in (a, b):
        await node.close()
        node.session.close()
    return np.array(rtts)


async def typed_throughput(endpoint: str) -> float:
    a = Node("bench", "src", open_client(endpoint))
    b = Node("bench", "dst", open_client(endpoint))
    count = [0]
    done = asyncio.Event()

    def on(_m) -> None:
        count[0] += 1
        if count[0] == N_THROUGHPUT:
            done.set()

    b.subscribe("xm/bench/src/bulk", on, fifo(), msgtype=BULK_TYPE)
    pub = a.publisher("xm/bench/src/bulk", BULK_TYPE)
    await asyncio.sleep(0.5)
    layout = msgs.make("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0)
    msg = msgs.make(BULK_TYPE, layout=layout, data=np.full(4080, 7, np.uint8))  # ~4 KB on the wire
    t0 = time.perf_counter()
    for i in range(N_THROUGHPUT):
        pub.put(msg)
        if i % 500 == 0:
            await asyncio.sleep(0)  # let the receiving side run, as a service loop would
    last, t_last = -1, time.perf_counter()
    while not done.is_set() and count[0] != last:  # stop when everything arrived or nothing more comes
        last = count[0]
        t_last = time.perf_counter()
        await asyncio.sleep(0.2)
    elapsed = (time.perf_counter() if done.is_set() else t_last) - t0
    print(f"typed throughput: {count[0]}/{N_THROUGHPUT} received, errors {dict(b.stats.errors)}")
    for node in (a, b):
        await node.close()
        node.session.close()
    return count[0] / elapsed


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    results = {}
    raw_lat = raw_pingpong(endpoint)
    typed_lat = asyncio.run(typed_pingpong(endpoint))
    raw_lat2 = raw_pingpong(endpoint)  # again, so drift of the machine shows up
    raw_lat = np.concatenate([raw_lat, raw_lat2])
    raw_tp = raw_throughput(endpoint)
    typed_tp = asyncio.run(typed_throughput(endpoint))
    router.close()
    for name, lat in (("raw", raw_lat), ("typed", typed_lat)):
        results[f"{name}_latency_p50_us"] = float(np.percentile(lat, 50) * 1e6)
        results[f"{name}_latency_p99_us"] = float(np.percentile(lat, 99) * 1e6)
    results["raw_throughput_msg_s"] = raw_tp
    results["typed_throughput_msg_s"] = typed_tp
    results["latency_p50_ratio"] = results["typed_latency_p50_us"] / results["raw_latency_p50_us"]
    results["latency_p99_ratio"] = results["typed_latency_p99_us"] / results["raw_latency_p99_us"]
    results["throughput_ratio"] = typed_tp / raw_tp
    results["targets"] = {"latency_p50_ratio_max": 1.15, "throughput_ratio_min": 0.8}
    Path(".bench").mkdir(exist_ok=True)
    Path(".bench/runtime.json").write_text(json.dumps(results, indent=2))
    print(f"{'':>8}{'p50 us':>10}{'p99 us':>10}{'4KB msg/s':>12}")
    for name in ("raw", "typed"):
        print(f"{name:>8}{results[f'{name}_latency_p50_us']:>10.0f}{results[f'{name}_latency_p99_us']:>10.0f}"
              f"{results[f'{name}_throughput_msg_s']:>12.0f}")
    print(f"ratios: latency p50 {results['latency_p50_ratio']:.2f}x (target <= 1.15), "
          f"p99 {results['latency_p99_ratio']:.2f}x, throughput {results['throughput_ratio']:.2f}x (target >= 0.8)")


if __name__ == "__main__":
    main()
