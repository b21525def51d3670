"""`xm record` and `xm replay`."""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import sys
import time
from pathlib import Path

from services.recorder.service import Recording, default_path
from services.recorder.writer import repair
from shared import keys
from shared.config import ConfigError, load_deployment
from shared.runtime import Node, open_client
from shared.runtime.logs import setup_logging


def record_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="xm record", description="Record keys of a running deployment to an MCAP "
                                     "file (ros2 profile; opens in Foxglove, rosbags, mcap-ros2-support).")
    parser.add_argument("--keys", default="xm/**", help="Zenoh key pattern (default: everything)")
    parser.add_argument("-o", "--output", help="output file (default: recordings/xm-<time>.mcap)")
    parser.add_argument("--duration", type=float, help="seconds to record (default: until Ctrl-C)")
    parser.add_argument("--deployment", default="deploy/sim.toml", help="deployment whose router to use")
    parser.add_argument("--repair", metavar="CUT_FILE", help="rewrite a recording cut by a crash into -o")
    args = parser.parse_args(argv)
    if args.repair:
        src = Path(args.repair)
        if not src.exists():
            print(f"error: {src} not found", file=sys.stderr)
            return 2
        dst = Path(args.output or src.with_suffix(".repaired.mcap"))
        n = repair(src, dst)
        print(f"recovered {n} messages into {dst}")
        return 0
    try:
        deployment = load_deployment(args.deployment)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.output) if args.output else default_path("recordings")
    return asyncio.run(_record(deployment.router, args.keys, out, args.duration))


async def _record(router: str, pattern: str, out: Path, duration: float | None) -> int:
    log = setup_logging("record")
    try:
        session = open_client(router)
    except Exception as exc:
        print(f"error: no router at {router} ({exc}); start the workcell with `xm up`", file=sys.stderr)
        return 2
    node = Node("recorder", f"cli{os.getpid()}", session, "wall", log)
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        asyncio.get_running_loop().add_signal_handler(sig, stop.set)
    rec = Recording(node, out, pattern, {"keys": pattern, "started": time.ctime()})
    t0 = time.monotonic()
    try:
        while not stop.is_set() and (duration is None or time.monotonic() - t0 < duration):
            await asyncio.sleep(0.5)
            total = sum(rec.writer.counts.values())
            print(f"\rrecording {out}: {time.monotonic() - t0:6.1f} s, {total} messages, "
                  f"{rec.writer.bytes / 1e6:.1f} MB", end="", file=sys.stderr, flush=True)
    finally:
        summary = rec.stop()
        await node.close()
        session.close()
    print(file=sys.stderr)
    seconds = max(summary["seconds"], 1e-9)
    print(f"{'key':<36}{'messages':>10}{'Hz':>8}")
    for key, n in sorted(summary["messages"].items()):
        print(f"{key:<36}{n:>10}{n / seconds:>8.1f}")
    for key, n in summary["unknown_keys"].items():
        print(f"{key:<36}{n:>10}   (not in the key registry: skipped)")
    print(f"wrote {summary['path']} ({summary['bytes'] / 1e6:.1f} MB)")
    return 0


def replay_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="xm replay", description="Republish an MCAP recording on its original "
                                     "keys with the original timing (xm/clock included).")
    parser.add_argument("file", help="MCAP recording")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1.0)")
    parser.add_argument("--keys", default="xm/**", help="only keys matching this pattern")
    parser.add_argument("--loop", action="store_true", help="start over at the end")
    parser.add_argument("--deployment", default="deploy/sim.toml", help="deployment whose router to use")
    args = parser.parse_args(argv)
    path = Path(args.file)
    if not path.exists():
        print(f"error: {path} not found", file=sys.stderr)
        return 2
    if args.rate <= 0:
        print("error: --rate must be positive", file=sys.stderr)
        return 2
    try:
        deployment = load_deployment(args.deployment)
        session = open_client(deployment.router)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:
        print(f"error: no router reachable ({exc}); start one with `xm up`", file=sys.stderr)
        return 2
    try:
        while True:
            n = _replay_once(session, path, args.rate, args.keys)
            print(f"replayed {n} messages from {path}", file=sys.stderr)
            if not args.loop:
                return 0
    except KeyboardInterrupt:
        return 0
    except ValueError as exc:
        print(f"error: {path} is not a readable MCAP file ({exc})", file=sys.stderr)
        return 2
    finally:
        session.close()


def _replay_once(session, path: Path, rate: float, pattern: str) -> int:
    from mcap.reader import make_reader

    pubs = {}
    count = 0
    with path.open("rb") as f:
        try:
            messages = make_reader(f).iter_messages(log_time_order=True)
            t_file0 = t_wall0 = None
            for _schema, channel, message in messages:
                if not keys.key_matches(pattern, channel.topic):
                    continue
                if t_file0 is None:
                    t_file0, t_wall0 = message.log_time, time.monotonic()
                delay = t_wall0 + (message.log_time - t_file0) * 1e-9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                pub = pubs.get(channel.topic) or pubs.setdefault(channel.topic,
                                                                 session.declare_publisher(channel.topic))
                pub.put(message.data)
                count += 1
        except Exception as exc:
            if count == 0:
                raise ValueError(str(exc)) from exc
    return count
