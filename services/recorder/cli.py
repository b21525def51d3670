"""`xm record` and `xm replay`: standalone clients of a running deployment's router."""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import sys
import time
from pathlib import Path

import zenoh

from services.recorder.segments import SEGMENT_S
from services.recorder.service import Recording, check_pattern, default_path
from services.recorder.writer import RecordingError, check_mcap, is_complete, read_messages, recording_files, repair
from shared import keys
from shared.client import add_connection_args, connect
from shared.runtime import Node
from shared.runtime.logs import setup_logging

EXIT_ERROR = 2


def _fail(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return EXIT_ERROR


# --- record ----------------------------------------------------------------------------------
def record_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="xm record",
        description="Record the keys of a running deployment into an MCAP file (ros2 profile, CDR bytes "
        "as on the wire; opens in Foxglove, rosbags and mcap-ros2-support). Stops at Ctrl-C or after "
        "--duration and prints messages and rates per key.",
        epilog="The recording is written in MCAP segments (FILE, FILE.seg0001.mcap, ...) of --segment "
        "seconds. A crash leaves every closed segment complete and the open one readable up to its last "
        "flushed chunk (at most ~1 s lost); `xm record --repair FILE` rewrites a cut segment as a complete "
        "file (the recorder service does that itself at start).")
    parser.add_argument("--keys", default="xm/**", metavar="PATTERN",
                        help="Zenoh key pattern to record (default: %(default)s, every registered key)")
    parser.add_argument("-o", "--output", metavar="FILE",
                        help="output file (default: recordings/xm-<date>-<time>.mcap)")
    parser.add_argument("--duration", type=float, metavar="S",
                        help="seconds to record (default: until Ctrl-C)")
    parser.add_argument("--segment", type=float, default=SEGMENT_S, metavar="S",
                        help="seconds per MCAP segment (default: %(default)s; 0: one file)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing output file")
    parser.add_argument("--repair", metavar="CUT_FILE",
                        help="instead of recording: rewrite a recording cut by a crash into -o "
                        "(default CUT_FILE with .repaired.mcap)")
    add_connection_args(parser)
    args = parser.parse_args(argv)
    if args.repair:
        return _repair(Path(args.repair), Path(args.output) if args.output else None, args.force)
    if args.duration is not None and args.duration <= 0:
        parser.error("--duration must be positive")
    try:
        check_pattern(args.keys)
    except ValueError as exc:
        parser.error(str(exc))
    out = Path(args.output) if args.output else default_path("recordings")
    if out.is_dir():
        out = default_path(out)
    if out.exists() and not args.force:
        return _fail(f"{out} exists; choose another -o or pass --force")
    return asyncio.run(_record(args, out))


def _repair(src: Path, dst: Path | None, force: bool) -> int:
    dst = dst or src.with_suffix(".repaired.mcap")
    if dst.exists() and not force:
        return _fail(f"{dst} exists; choose another -o or pass --force")
    try:
        check_mcap(src)
        complete = is_complete(src)
        n = repair(src, dst)
    except (RecordingError, OSError) as exc:
        return _fail(str(exc))
    state = "was complete already" if complete else "had no footer (cut)"
    print(f"{src} {state}: {n} messages written to {dst}")
    return 0


async def _record(args: argparse.Namespace, out: Path) -> int:
    session, router, name = connect(args)
    if session is None:
        return EXIT_ERROR
    log = setup_logging("record", "WARNING")  # the terminal is for the progress line
    node = Node("recorder", f"cli-{os.getpid()}", session, "wall", log)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    tty = sys.stderr.isatty()
    try:
        rec = Recording(node, out, args.keys, {"deployment": name, "deployment_file": args.deployment,
                                               "router": router, "recorder": "xm record"}, args.segment)
    except (ValueError, OSError) as exc:
        await node.close()
        session.close()
        return _fail(str(exc))
    t0 = time.monotonic()
    try:
        while not stop.is_set():
            left = None if args.duration is None else args.duration - (time.monotonic() - t0)
            if left is not None and left <= 0:
                break
            try:
                await asyncio.wait_for(stop.wait(), 0.5 if left is None else min(0.5, left))
            except TimeoutError:
                pass
            if tty:
                s = rec.writer.summary()
                print(f"\rrecording {out}: {time.monotonic() - t0:6.1f} s, {sum(s.messages.values())} "
                      f"messages on {len(s.messages)} keys, {s.bytes / 1e6:.1f} MB  ", end="",
                      file=sys.stderr, flush=True)
    finally:
        summary = await rec.stop()
        await node.close()
        session.close()
    if tty:
        print(file=sys.stderr)
    print(summary_table(summary))
    if not summary["messages"]:
        print(f"warning: nothing was published on {args.keys} (is the workcell running on {router}?)",
              file=sys.stderr)
    return 0


def summary_table(summary: dict) -> str:
    """The per-key table printed at the end of `xm record`."""
    lines = [f"{'key':<40}{'messages':>10}{'Hz':>9}"]
    for key, n in sorted(summary["messages"].items()):
        lines.append(f"{key:<40}{n:>10}{summary['rates_hz'].get(key, 0.0):>9.1f}")
    for kind, label in (("unknown_keys", "not in the key registry: skipped"),
                        ("malformed", "did not decode as its type: skipped")):
        for key, n in sorted(summary.get(kind, {}).items()):
            lines.append(f"{key:<40}{n:>10}   ({label})")
    total = sum(summary["messages"].values())
    lines.append(f"wrote {summary['path']}: {total} messages, {summary['bytes'] / 1e6:.2f} MB "
                 f"in {summary['seconds']:.1f} s")
    return "\n".join(lines)


# --- replay ----------------------------------------------------------------------------------
def replay_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="xm replay",
        description="Republish an MCAP recording's stored bytes on their original keys with the original "
        "timing (receive times) scaled by --rate. xm/clock is replayed too, so services of a sim-clock "
        "deployment follow the replay; do not run the world at the same time.",
        epilog="A segmented recording is replayed as one: give its first segment (the others are found "
        "beside it), its directory, or the segment files. A segment cut by a crash is replayed up to "
        "its last flushed chunk.")
    parser.add_argument("file", nargs="+", help="MCAP recording (from xm record or the recorder service): "
                        "a file, a directory of recordings, or several segment files")
    parser.add_argument("--rate", type=float, default=1.0,
                        help="playback speed factor (default: %(default)s)")
    parser.add_argument("--keys", default="xm/**", metavar="PATTERN",
                        help="replay only keys matching this Zenoh pattern (default: %(default)s)")
    parser.add_argument("--loop", action="store_true", help="start over at the end until Ctrl-C")
    add_connection_args(parser)
    args = parser.parse_args(argv)
    if not args.rate > 0:
        parser.error("--rate must be positive")
    path = Path(args.file[0]) if len(args.file) == 1 else Path(args.file[0]).parent
    try:
        files = recording_files(args.file if len(args.file) > 1 else args.file[0])
    except (RecordingError, OSError) as exc:
        return _fail(str(exc))
    session, _, _ = connect(args)
    if session is None:
        return EXIT_ERROR
    publishers: dict[str, zenoh.Publisher] = {}
    sent = [0]  # messages published, also those of a pass cut short by Ctrl-C
    passes = 0
    try:
        while True:
            cut: list[str] = []
            n = _replay_once(session, publishers, files, args.rate, args.keys, cut, sent)
            passes += 1
            for line in cut if passes == 1 else []:
                print(f"warning: {line}", file=sys.stderr)
            if n == 0:
                print(f"{path}: no messages on keys matching {args.keys}", file=sys.stderr)
                return 1
            if not args.loop:
                break
    except KeyboardInterrupt:
        pass
    except RecordingError as exc:
        return _fail(str(exc))
    except Exception as exc:  # a damaged file the readers reject
        return _fail(f"{path}: unreadable MCAP ({type(exc).__name__}: {exc})")
    finally:
        for pub in publishers.values():
            pub.undeclare()
        session.close()
    print(f"replayed {sent[0]} messages on {len(publishers)} keys from {path}"
          + (f" ({passes} passes)" if passes > 1 else ""), file=sys.stderr)
    return 0


def _replay_once(session: zenoh.Session, publishers: dict[str, zenoh.Publisher], files: list[Path],
                 rate: float, pattern: str, cut: list[str], sent: list[int]) -> int:
    count = 0
    t_file0: int | None = None
    t_wall0 = 0.0
    tty = sys.stderr.isatty()
    path = files[0]
    for stored in read_messages(files, cut=cut):
        if not keys.key_matches(pattern, stored.key):
            continue
        if t_file0 is None:
            t_file0, t_wall0 = stored.log_time, time.monotonic()
        delay = t_wall0 + (stored.log_time - t_file0) * 1e-9 / rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        pub = publishers.get(stored.key)
        if pub is None:  # BLOCK: a replay is as lossless as the recording was
            pub = publishers[stored.key] = session.declare_publisher(
                stored.key, congestion_control=zenoh.CongestionControl.BLOCK)
        pub.put(stored.data)
        count += 1
        sent[0] += 1
        if tty and count % 200 == 0:
            print(f"\rreplaying {path}: {(stored.log_time - t_file0) * 1e-9:7.1f} s, {count} messages  ",
                  end="", file=sys.stderr, flush=True)
    if tty and count:
        print(file=sys.stderr)
    return count
