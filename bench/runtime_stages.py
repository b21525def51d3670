"""P1 per stage: the CPU time one message costs in each stage of the typed runtime.

Runs each stage alone in a loop on this thread (``time.thread_time_ns``, best of ``--repeat``),
so the figures hold on a busy host where wall-clock ratios (bench/runtime.py) do not: publishing
(serialize, join, the Zenoh put, the published meter, and ``Publisher.put`` whole) and receiving
(the sample's key and payload copy, decoding, validation, the received meter, and the inline and
queued Zenoh callbacks whole, the loop's hand-over excluded) of a 64 B string (ping-pong) and a
4 kB byte array (throughput), against what raw zenoh-python spends in the same calls. A session
to a router on loopback carries the puts (no subscriber: the put's cost in this process only);
the receive callbacks get samples built here. Writes .bench/runtime_stages.json.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere

from bench.runtime import BULK_TYPE, PING_TYPE, bulk_message, free_port  # noqa: E402
from shared import msgs  # noqa: E402
from shared.runtime import Node, fifo, open_client, open_router, validate  # noqa: E402
from shared.runtime.stats import RateMeter  # noqa: E402


def cost_us(func: Callable[[], object], n: int, repeat: int) -> float:
    """CPU microseconds per call of ``func`` on this thread, best of ``repeat`` loops of ``n``."""
    for _ in range(n // 10):
        func()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.thread_time_ns()
        for _ in range(n):
            func()
        best = min(best, (time.thread_time_ns() - t0) / n)
    return best / 1000


class Sample:
    """What a subscription callback reads of a zenoh.Sample."""

    def __init__(self, key: str, payload: bytes) -> None:
        self.key_expr = zenoh.KeyExpr(key)
        self.payload = zenoh.ZBytes(payload)


class NoLoop:
    """Stands in for the event loop: the queued callback's hand-over is not measured here."""

    def call_soon_threadsafe(self, _callback: Callable) -> None:
        pass


def stages(node: Node, name: str, msgtype: str, msg: object, n: int, repeat: int) -> dict[str, float]:
    key = f"xm/bench/stages/{name}"
    write = msgs.pieces_writer(msgtype)
    pieces, _ = write(msg)
    payload = b"".join(pieces)
    pub = node.publisher(key, msgtype)
    raw = node.session.declare_publisher(f"{key}/raw")
    meter = RateMeter()
    decode = msgs.decoder(msgtype)
    decoded = decode(payload)
    check = validate.checker(msgtype)  # None: the type has nothing to check
    sample = Sample(key, payload)
    inline = node.subscribe(f"{key}/in", lambda _m: None, fifo(), msgtype=msgtype, inline=True)
    queued = node.subscribe(f"{key}/q", lambda _m: None, fifo(), msgtype=msgtype)
    queued._loop = NoLoop()
    on_queued = queued._queue_callback()

    def queue_one() -> None:
        on_queued(sample)
        queued._queue.clear()
        queued._scheduled = False

    run = {
        "publish: serialize": lambda: write(msg),
        "publish: join pieces": lambda: b"".join(pieces),
        "publish: zenoh put (raw's whole cost)": lambda: raw.put(payload),
        "publish: meter tick": lambda: meter.tick(time.monotonic()),
        "publish: Publisher.put whole": lambda: pub.put(msg),
        "receive: key and payload copy": lambda: (str(sample.key_expr), sample.payload.to_bytes()),
        "receive: decode": lambda: decode(payload),
        "receive: validate (what the type can fail)": (lambda: check(decoded, time.time())) if check else None,
        "receive: inline callback whole": lambda: inline._on_inline(sample),
        "receive: queued callback whole (fifo, no hand-over)": queue_one,
    }
    out = {stage: round(cost_us(func, n, repeat), 3) if func else 0.0 for stage, func in run.items()}
    raw.undeclare()
    return out


async def measure(n: int, repeat: int) -> dict:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    node = Node("bench", "stages", open_client(endpoint))
    try:
        return {"64 B string": stages(node, "ping", PING_TYPE, msgs.make(PING_TYPE, data="x" * 56), n, repeat),
                "4 kB byte array": stages(node, "bulk", BULK_TYPE, bulk_message(4096), n, repeat)}
    finally:
        await node.close()
        node.session.close()
        router.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-n", type=int, default=50_000, help="calls per loop (default %(default)s)")
    parser.add_argument("--repeat", type=int, default=5, help="loops per stage, the best counts (default %(default)s)")
    args = parser.parse_args()
    res = asyncio.run(measure(args.n, args.repeat))
    Path(".bench").mkdir(exist_ok=True)
    Path(".bench/runtime_stages.json").write_text(json.dumps(res, indent=2))
    for what, costs in res.items():
        print(what)
        for stage, us in costs.items():
            print(f"  {stage:<55}{us:>7.2f} us")


if __name__ == "__main__":
    main()
