"""Memory of processes exchanging 300 kB images through the shared-memory pool (bench/runtime.py).

A router, a subscriber and a publisher in three processes, as in a deployment: the publisher puts
typed 300 kB images at ``RATE_HZ`` for the run while each process's RSS is sampled; then the
publisher is killed (-9) and restarted a few times, each run putting images for a few seconds, to
measure what a restart leaves mapped in the subscriber and the router (eclipse-zenoh/zenoh#2787)
and what stays in /dev/shm once every process exited (Zenoh removes a dead process's segments when
the next pool on the host is opened).
"""

from __future__ import annotations

import asyncio
import multiprocessing as mp
import socket
import time
from pathlib import Path

import numpy as np

from shared import msgs
from shared.runtime import Node, fifo, open_client, open_router, shm

KEY = "xm/bench/cam/image"
IMAGE = "sensor_msgs/msg/Image"
RATE_HZ = 200.0  # about a rig's seven 30 fps cameras
SAMPLE_S = 2.0
RESTART_RUN_S = 3.0


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def shm_files_mb() -> float:
    return sum(p.stat().st_size for p in Path("/dev/shm").iterdir() if p.is_file()) / 2**20


def _router(endpoint: str, ready, stop) -> None:
    router = open_router(endpoint)
    ready.set()
    stop.wait()
    router.close()


def _subscriber(endpoint: str, received, ready, stop) -> None:
    async def run() -> None:
        node = Node("bench", "sub", open_client(endpoint))

        def on(_msg) -> None:
            with received.get_lock():
                received.value += 1

        node.subscribe(KEY, on, fifo(), msgtype=IMAGE)
        ready.set()
        while not stop.is_set():
            await asyncio.sleep(0.1)
        await node.close()
        node.session.close()

    asyncio.run(run())


def _publisher(endpoint: str, seconds: float, sent, from_pool, putting) -> None:
    async def run() -> None:
        node = Node("bench", "pub", open_client(endpoint))
        pub = node.publisher(KEY, IMAGE, block=True)
        await asyncio.sleep(0.5)
        frames = [msgs.make(IMAGE, header=msgs.header(time.time(), "cam0"), height=480, width=625, encoding="mono8",
                            is_bigendian=0, step=625, data=np.full(480 * 625, i, np.uint8)) for i in range(8)]
        t0 = time.monotonic()
        i = 0
        while (now := time.monotonic()) < t0 + seconds:
            msg = frames[i % len(frames)]
            msg.header = msgs.header(time.time(), "cam0")
            pub.put(msg)
            putting.set()
            i += 1
            await asyncio.sleep(max(0.0, t0 + i / RATE_HZ - now))
        sent.value += i
        from_pool.value += pub.shm_sent
        await asyncio.sleep(0.5)
        await node.close()
        node.session.close()

    asyncio.run(run())


def measure(seconds: float, restarts: int) -> dict:
    """RSS of router, subscriber and publisher over ``seconds`` of streaming, then the subscriber's
    and router's RSS after each of ``restarts`` publisher restarts."""
    ctx = mp.get_context("spawn")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    stop = ctx.Event()
    received, sent, from_pool = ctx.Value("q", 0), ctx.Value("q", 0), ctx.Value("q", 0)
    shm_before = shm_files_mb()
    router_up, sub_up = ctx.Event(), ctx.Event()
    router = ctx.Process(target=_router, args=(endpoint, router_up, stop))
    router.start()
    if not router_up.wait(60):
        raise RuntimeError("the router process did not start in 60 s")
    sub = ctx.Process(target=_subscriber, args=(endpoint, received, sub_up, stop))
    sub.start()
    if not sub_up.wait(60):
        raise RuntimeError("the subscriber process did not start in 60 s")
    first_put = ctx.Event()  # held here: the child unpickles it after start()
    pub = ctx.Process(target=_publisher, args=(endpoint, seconds, sent, from_pool, first_put))
    pub.start()
    samples = []
    t0 = time.monotonic()
    while pub.is_alive():
        samples.append({"t_s": round(time.monotonic() - t0, 1), "received": received.value,
                        **{name: rss_mb(p.pid) for name, p in (("router_mb", router), ("subscriber_mb", sub),
                                                                ("publisher_mb", pub)) if p.is_alive()},
                        "dev_shm_mb": shm_files_mb() - shm_before})
        time.sleep(SAMPLE_S)
    pub.join()
    streamed = {"sent": sent.value, "from_pool": from_pool.value, "received": received.value}
    after_restarts = [{"router_mb": rss_mb(router.pid), "subscriber_mb": rss_mb(sub.pid)}]
    killed_runs: list[int] = []  # images received from each killed publisher
    for _ in range(restarts):  # killed like the soak kills a service: kill -9 mid-stream
        putting, before = ctx.Event(), received.value
        p = ctx.Process(target=_publisher, args=(endpoint, 3600.0, sent, from_pool, putting))
        p.start()
        if not putting.wait(60):
            raise RuntimeError("a restarted publisher put nothing in 60 s")
        time.sleep(RESTART_RUN_S)
        p.kill()
        killed_runs.append(received.value - before)
        p.join()
        after_restarts.append({"router_mb": rss_mb(router.pid), "subscriber_mb": rss_mb(sub.pid),
                               "dev_shm_mb": shm_files_mb() - shm_before})
    stop.set()
    sub.join(10)
    router.join(10)
    shm_left = shm_files_mb() - shm_before
    steady = [s for s in samples if s["t_s"] >= seconds * 0.25 and "publisher_mb" in s]
    growth = {name: (steady[-1][name] - steady[0][name]) if len(steady) >= 2 else None
              for name in ("router_mb", "subscriber_mb", "publisher_mb")}
    per_restart = {name: (after_restarts[-1][name] - after_restarts[0][name]) / max(restarts, 1)
                   for name in ("router_mb", "subscriber_mb")}
    return {"seconds": seconds, "rate_hz": RATE_HZ, "pool_mb": shm.POOL_BYTES / 2**20, **streamed,
            "samples": samples, "steady_growth_mb": growth, "after_restarts": after_restarts,
            "growth_per_restart_mb": per_restart, "dev_shm_left_mb": shm_left,
            "received_per_killed_publisher": killed_runs}


def report(r: dict) -> None:
    print(f"SHM run: {r['sent']} images of 300 kB put in {r['seconds']:.0f} s and restarts, {r['from_pool']} from the "
          f"pool, {r['received']} received")
    print("RSS growth from a quarter of the run to its end: " + ", ".join(
        f"{k[:-3]} {v:+.1f} MB" for k, v in r["steady_growth_mb"].items() if v is not None))
    print("per publisher restart (kill -9): " + ", ".join(
        f"{k[:-3]} {v:+.1f} MB" for k, v in r["growth_per_restart_mb"].items())
          + f"; left in /dev/shm once every process exited: {r['dev_shm_left_mb']:.1f} MB")
