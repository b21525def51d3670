"""``xm export lerobot`` and ``xm import lerobot`` (docs/lerobot.md)."""

from __future__ import annotations

import argparse
import sys
import time

from interop import lerobot_format as fmt
from interop.lerobot_export import ExportOptions, export
from interop.lerobot_import import import_dataset, save_demos
from learning.dataset import DatasetError


def export_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="xm export", description="export recorded demonstrations")
    sub = parser.add_subparsers(dest="format", required=True)
    p = sub.add_parser("lerobot", help="LeRobot dataset v3 (Parquet tables, MP4 camera streams)")
    p.add_argument("recordings", nargs="+",
                   help="MCAP recordings: first segments (the rest are found beside them) or directories of them")
    p.add_argument("-o", "--out", required=True, help="dataset directory (an earlier export there is replaced)")
    p.add_argument("--fps", type=int, default=50, help="frames per second: the demonstrations' time step")
    p.add_argument("--robot", default="auto",
                   help="robot state key (default: the recording's xm/robot/*/state); 'none': no joints")
    p.add_argument("--cameras", default=None,
                   help="comma-separated cameras (default: every camera of the first recording); 'none': no video")
    p.add_argument("--vcodec", default="libsvtav1", help="video codec (LeRobot's default AV1; libx264, mpeg4, ...)")
    p.add_argument("--robot-type", default=None, help="info.json robot_type")
    args = parser.parse_args(argv)
    cams = None if args.cameras is None else ([] if args.cameras == "none" else args.cameras.split(","))
    opts = ExportOptions(fps=args.fps, robot=None if args.robot == "none" else args.robot, cameras=cams,
                         vcodec=args.vcodec, robot_type=args.robot_type)
    t0 = time.monotonic()
    try:
        res = export(args.recordings, args.out, opts)
    except (DatasetError, FileExistsError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for line in res.report:
        print(f"note: {line}")
    for line in res.skipped:
        print(line)
    print(f"wrote {args.out}: {res.episodes} episodes, {res.frames} frames at {args.fps} fps, "
          f"{len(res.skipped)} skipped, {time.monotonic() - t0:.1f} s; features: {', '.join(res.features)}")
    return 0


def import_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="xm import", description="import demonstrations")
    sub = parser.add_subparsers(dest="format", required=True)
    p = sub.add_parser("lerobot", help="a LeRobot v3 dataset written by `xm export lerobot`")
    p.add_argument("dataset", help="dataset directory (meta/info.json inside)")
    p.add_argument("-o", "--out", default=None,
                   help="directory for the demonstrations, one .npz each (default: NAME-demos beside DATASET)")
    args = parser.parse_args(argv)
    try:
        demos = import_dataset(args.dataset)
    except (fmt.FormatError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    paths = save_demos(demos, args.out or f"{args.dataset.rstrip('/')}-demos")
    steps = sum(d.steps for d in demos)
    print(f"read {len(demos)} demonstrations ({steps} steps); wrote {len(paths)} files to {paths[0].parent}"
          if paths else "the dataset has no episodes")
    return 0
