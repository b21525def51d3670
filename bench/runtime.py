"""P1: the typed runtime against raw zenoh-python in the same run.

Ping-pong latency (64 B payload, p50/p99) and one-way throughput of 4 kB and 300 kB messages
(a camera frame), through a router on loopback as in a deployment. Throughput publishers block
when the transport is congested (raw and typed alike), so both count delivered capacity rather
than what a flood left after drops. The typed runtime is measured
both ways a subscription can run: handlers on the event loop (the default) and ``inline`` on
Zenoh's threads (shared/runtime/node.py). Writes .bench/runtime.json; targets: latency <= 1.15x
raw, throughput >= 0.8x raw.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh
from zenoh.shm import BlockOn, GarbageCollect, ShmProvider

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere

from shared import msgs  # noqa: E402
from shared.runtime import Node, fifo, latest, open_client, open_router, shm  # noqa: E402

N_PING = 2000
N_WARM = 200
N_THROUGHPUT = 20000
N_THROUGHPUT_LARGE = 2000
SIZES = (4096, 300_000)  # a 4 kB message, a camera frame
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


def raw_throughput(endpoint: str, size: int, from_pool: bool = False) -> float:
    """Raw puts of ``size`` bytes. ``from_pool``: each payload copied into a buffer of a
    shared-memory pool of the typed runtime's size and put from there (as bytes when the pool is
    full), zenoh-python's own way for a large payload to a process on the same host."""
    a, b = open_client(endpoint), open_client(endpoint)
    count = [0]
    done = threading.Event()
    n = n_for(size)

    def on(_s) -> None:
        count[0] += 1
        if count[0] == n:
            done.set()

    b.declare_subscriber("bench/raw/bulk", on)
    pub = a.declare_publisher("bench/raw/bulk", congestion_control=zenoh.CongestionControl.BLOCK)
    provider = ShmProvider.default_backend(shm.POOL_BYTES) if from_pool else None
    time.sleep(0.5)
    payload = b"y" * size
    copied = 0
    t0 = time.perf_counter()
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
    elapsed = wait_counted(count, done.is_set, t0)
    a.close()
    b.close()
    print(f"raw throughput {size} B{' from a shared-memory pool' if from_pool else ''}: {count[0]}/{n} received"
          + (f", {copied} copied (pool full)" if from_pool else ""))
    return count[0] / elapsed


def shm_throughput(size: int) -> dict[str, float]:
    """Raw zenoh-python at ``size`` through a router with Zenoh's shared-memory transport on: each
    message put from a buffer of the publisher's SHM pool, against plain bytes through the same
    router. The deployment keeps SHM off (shared/runtime/zsession.py): this is the measurement."""
    def config(mode: str, **endpoints: list[str]) -> zenoh.Config:
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("transport/shared_memory/enabled", "true")
        for k, v in endpoints.items():
            conf.insert_json5(f"{k}/endpoints", json.dumps(v))
        return conf

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(config("router", listen=[endpoint]))
    a, b = zenoh.open(config("client", connect=[endpoint])), zenoh.open(config("client", connect=[endpoint]))
    count, shm_seen = [0], [0]

    def on(sample: zenoh.Sample) -> None:
        count[0] += 1
        shm_seen[0] += sample.payload.as_shm() is not None

    b.declare_subscriber("bench/shm/bulk", on)
    pub = a.declare_publisher("bench/shm/bulk", congestion_control=zenoh.CongestionControl.BLOCK)
    provider = ShmProvider.default_backend(64 * 1024 * 1024)
    time.sleep(0.5)
    n, payload, out = n_for(size), b"y" * size, {}
    for label in ("shm", "bytes"):
        count[0] = shm_seen[0] = 0
        t0 = time.perf_counter()
        for _ in range(n):
            if label == "shm":
                pub.put(provider.alloc(size, policy=BlockOn(GarbageCollect())))
            else:
                pub.put(payload)
        out[label] = count[0] / wait_counted(count, lambda: count[0] >= n, t0)
        out[f"{label}_delivered_as_shm"] = shm_seen[0]
    for s in (a, b, router):
        s.close()
    return out


def n_for(size: int) -> int:
    return N_THROUGHPUT if size <= 4096 else N_THROUGHPUT_LARGE


def wait_counted(count: list[int], done, t0: float) -> float:
    """Seconds from ``t0`` until everything arrived or nothing more came for 0.2 s."""
    last, t_last = -1, time.perf_counter()
    while not done() and count[0] != last:
        last, t_last = count[0], time.perf_counter()
        time.sleep(0.2)
    return (time.perf_counter() if done() else t_last) - t0


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
            got.wait(2.0)
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
            await asyncio.wait_for(waiter[0], 2.0)
            if i >= N_WARM:
                rtts.append(time.perf_counter() - t0)
    for node in (a, b):
        await node.close()
        node.session.close()
    return np.array(rtts)


async def typed_throughput(endpoint: str, size: int, inline: bool) -> float:
    a = Node("bench", "src", open_client(endpoint))
    b = Node("bench", "dst", open_client(endpoint))
    count = [0]
    n = n_for(size)
    lock = threading.Lock()

    def on(_m) -> None:
        with lock:
            count[0] += 1

    b.subscribe("xm/bench/src/bulk", on, fifo(), msgtype=BULK_TYPE, inline=inline)
    pub = a.publisher("xm/bench/src/bulk", BULK_TYPE, block=True)
    await asyncio.sleep(0.5)
    layout = msgs.make("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0)
    msg = msgs.make(BULK_TYPE, layout=layout, data=np.full(size - 16, 7, np.uint8))  # size bytes on the wire
    t0 = time.perf_counter()
    for i in range(n):
        pub.put(msg)
        if i % 500 == 0:
            await asyncio.sleep(0)  # let the receiving side run, as a service loop would
    last, t_last = -1, time.perf_counter()
    while count[0] < n and count[0] != last:  # stop when everything arrived or nothing more comes
        last, t_last = count[0], time.perf_counter()
        await asyncio.sleep(0.2)
    elapsed = (time.perf_counter() if count[0] >= n else t_last) - t0
    print(f"typed{' inline' if inline else ''} throughput {size} B: {count[0]}/{n} received, "
          f"errors {dict(b.stats.errors)}")
    for node in (a, b):
        await node.close()
        node.session.close()
    return count[0] / elapsed


def percentiles(lat: np.ndarray) -> dict:
    return {"p50_us": float(np.percentile(lat, 50) * 1e6), "p99_us": float(np.percentile(lat, 99) * 1e6)}


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    raw = [raw_pingpong(endpoint)]
    lat = {"loop": asyncio.run(typed_pingpong(endpoint, False)), "inline": asyncio.run(typed_pingpong(endpoint, True))}
    raw.append(raw_pingpong(endpoint))  # again, so drift of the machine shows up
    lat["raw"] = np.concatenate(raw)
    tp: dict[str, dict[str, float]] = {}
    for size in SIZES:
        tp[str(size)] = {"raw": raw_throughput(endpoint, size),
                         "loop": asyncio.run(typed_throughput(endpoint, size, False)),
                         "inline": asyncio.run(typed_throughput(endpoint, size, True))}
    router.close()
    shm = shm_throughput(SIZES[-1])
    res: dict = {"latency_us": {k: percentiles(v) for k, v in lat.items()}, "throughput_msg_s": tp,
                 "shared_memory_raw_msg_s": shm, "loadavg_1m": os.getloadavg()[0]}
    res["ratios"] = {path: {
        "latency_p50": res["latency_us"][path]["p50_us"] / res["latency_us"]["raw"]["p50_us"],
        "latency_p99": res["latency_us"][path]["p99_us"] / res["latency_us"]["raw"]["p99_us"],
        **{f"throughput_{size}": tp[str(size)][path] / tp[str(size)]["raw"] for size in SIZES}}
        for path in ("loop", "inline")}
    res["targets"] = {"latency_ratio_max": 1.15, "throughput_ratio_min": 0.8}
    Path(".bench").mkdir(exist_ok=True)
    Path(".bench/runtime.json").write_text(json.dumps(res, indent=2))
    print(f"{'':>8}{'p50 us':>10}{'p99 us':>10}" + "".join(f"{f'{s} B msg/s':>16}" for s in SIZES))
    for path in ("raw", "loop", "inline"):
        print(f"{path:>8}{res['latency_us'][path]['p50_us']:>10.0f}{res['latency_us'][path]['p99_us']:>10.0f}"
              + "".join(f"{tp[str(s)][path]:>16.0f}" for s in SIZES))
    print(f"raw {SIZES[-1]} B with the shared-memory transport: {shm['shm']:.0f} msg/s from SHM buffers, "
          f"{shm['bytes']:.0f} msg/s from bytes ({shm['shm_delivered_as_shm']} delivered as SHM)")
    for path, r in res["ratios"].items():
        print(f"{path} / raw: " + ", ".join(f"{k} {v:.2f}x" for k, v in r.items())
              + " (targets: latency <= 1.15x, throughput >= 0.8x)")


if __name__ == "__main__":
    main()
