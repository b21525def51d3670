"""``xm calibrate``: calibrate the camera rig with a ChArUco board and write the rig calibration file.

Simulated workcell (``xm up deploy/sim.toml`` running): the world moves its board body through
the calibration sequence and each pose is rendered at the deployment's ``[calibration]`` size
(``--source world``, default) or taken from camhub's live frames (``--source camhub``, at
camhub's resolution). Hardware: ``--record`` captures from camhub while a person waves the board.
``--source model`` renders the sequence from the world model without a running deployment;
``--frames DIR`` calibrates from saved frame sets (``--save-frames DIR`` writes them).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from calibration import capture
from calibration import report as rep
from calibration.board import Settings, load_settings
from calibration.detect import Collector
from calibration.init import CaptureUnusableError
from calibration.pipeline import calibrate
from services.world import calibration_sequence as calseq
from services.world import render
from services.world.model import camera_specs
from shared.calibration import save
from shared.charuco import BoardError
from shared.client import add_connection_args, connect


def true_cameras(width: int, height: int) -> dict:
    """The simulator's cameras in OpenCV's pixel convention. A renderer that draws each camera's K
    through an explicit OpenGL frustum (``render.gl_frustum``) renders K exactly; MuJoCo's own
    camera (``fovy``) puts the principal point at (w/2, h/2) in pixel-edge coordinates, which is
    (w/2 - 0.5, h/2 - 0.5) from pixel centres (rendered corners agree to 0.01 px)."""
    offset = 0.0 if hasattr(render, "gl_frustum") else 0.5
    out = {}
    for spec in camera_specs(width, height):
        K = spec.K.copy()
        K[:2, 2] -= offset
        out[spec.name] = (K, spec.world_T_cam)
    return out


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="xm calibrate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_connection_args(p)
    p.add_argument("--source", choices=("world", "camhub", "model"), default="world",
                   help="where simulated frames come from (default: %(default)s)")
    p.add_argument("--record", action="store_true", help="hardware: capture from camhub while the board is waved")
    p.add_argument("--duration", type=float, default=60.0, help="--record: seconds of waving (default: %(default)s)")
    p.add_argument("--every", type=float, default=0.5,
                   help="--record: seconds between frame sets (default: %(default)s)")
    p.add_argument("--frames", type=Path, metavar="DIR", help="calibrate from frame sets saved in DIR")
    p.add_argument("--save-frames", type=Path, metavar="DIR", help="also save the captured frame sets in DIR")
    p.add_argument("--count", type=int, help="frame sets of the simulated sequence (default: [calibration] frames)")
    p.add_argument("--model", choices=("full", "centred"), help="camera model (default: [calibration] model)")
    p.add_argument("--seed", type=int, default=0, help="simulated sequence seed (default: %(default)s)")
    p.add_argument("--output", type=Path, default=Path("runs/calibration/rig.json"),
                   help="calibration file; the report goes beside it (default: %(default)s)")
    p.add_argument("--no-truth", action="store_true", help="do not grade against the simulator's cameras")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        settings = load_settings(args.deployment)
    except BoardError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    settings = Settings(settings.board, settings.registration, settings.width, settings.height,
                        args.count or settings.frames, args.model or settings.model)
    collector = Collector(settings.board)

    def sink(index: int, images: list) -> None:
        if args.save_frames:
            capture.save_frames(args.save_frames, index, [f"cam{c}" for c in range(len(images))], images)
        collector.add(index, images)

    def progress(index: int) -> None:
        print(f"\rframe set {index + 1}", end="", file=sys.stderr, flush=True)

    simulated = not (args.record or args.frames)
    t0 = time.perf_counter()
    try:
        names = capture_frames(args, settings, sink, progress)
    except (capture.CaptureError, OSError) as exc:
        print(f"\nerror: {exc}", file=sys.stderr)
        return 2
    capture_s = time.perf_counter() - t0
    print(file=sys.stderr)
    try:
        det = collector.result(names)
        world_T_board = calseq.registration_pose(settings.board, settings.registration)
        cal = calibrate(det, settings.board, world_T_board, registration_frame=0, model=settings.model)
    except (CaptureUnusableError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        small = collector.det is not None and min(w for w, _ in collector.det.image_sizes) < 640
        if small:
            print(f"note: the frames are {collector.det.image_sizes[0][0]}x{collector.det.image_sizes[0][1]}; the "
                  "board's markers need about 640x480 (in the simulation use --source world)", file=sys.stderr)
        return 1
    truth = true_cameras(*det.image_sizes[0]) if simulated and not args.no_truth else None
    report = rep.build(cal, det, truth, {"capture_s": capture_s - collector.seconds, "detect_s": collector.seconds,
                                          "calibration_s": collector.seconds + sum(cal.seconds.values())})
    args.output.parent.mkdir(parents=True, exist_ok=True)
    save(cal.rig, args.output)
    json_path, png_path = args.output.with_suffix(".report.json"), args.output.with_suffix(".report.png")
    rep.write(report, cal, det, json_path, png_path)
    print(rep.text(report))
    print(f"wrote {args.output}, {json_path} and {png_path}")
    return 0


def capture_frames(args: argparse.Namespace, settings: Settings, sink, progress) -> list[str]:
    if args.frames:
        return capture.from_folder(args.frames, sink, progress)
    if args.source == "model" and not args.record:
        return capture.from_model(settings, args.seed, sink, progress)
    session, _, _ = connect(args)
    if session is None:
        raise capture.CaptureError("no router (see above)")
    try:
        if args.record:
            return capture.record(session, args.duration, args.every, sink, progress, lambda text: input(text + " "))
        if args.source == "camhub":
            return capture.from_camhub_sim(session, settings, args.seed, sink, progress)
        return capture.from_world(session, settings, args.seed, sink, progress)
    finally:
        session.close()
