"""The simulated camera rig: render time per frame set (7 cameras) at 256x192 (the live sim's
size) and 640x480 (calibration runs, detector training), full frames and per-camera windows
around the hands (thesis 5.4), plus the JPEG encoding camhub does per frame set.

States come from one demonstration of the scripted teacher (hands moving); the windows are those
camhub computes from the hands' keypoints with its default margin, taken here from the simulator
(a perfect reconstruction). Medians of the process's CPU time over the frame sets (wall time
beside it: on a shared machine it measures the neighbours); ratios against 256x192 full frames
measured in the same run. Writes .bench/camhub.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere

from services.camhub.camera_info import encode_jpeg  # noqa: E402
from services.camhub.roi import CameraGeometry, RoiParams, rig_windows  # noqa: E402
from services.world.render import SceneRenderer, snapshot  # noqa: E402
from services.world.sim import WorldSim  # noqa: E402

SIZES = ((256, 192), (640, 480))


def states(n: int, seed: int) -> list:
    """n snapshots spread over the first demonstration, with the hands' keypoints of each."""
    sim = WorldSim("assembly", seed=seed)
    steps = max(1, int(sim.teacher.duration / sim.physics_dt / n))
    out = []
    for _ in range(n):
        sim.step(steps)
        out.append((snapshot(sim.task, sim.data, sim.robot_name, seed, sim.demo, sim.teacher.tactile_hand),
                    sim.hand_keypoints().reshape(-1, 3)))
    return out


def measure(width: int, height: int, frames: list, roi: bool) -> dict:
    renderer = SceneRenderer("assembly", width, height)
    cams = [CameraGeometry(c.name, width, height, c.K, np.zeros(5), c.world_T_cam) for c in renderer.cameras]
    params = RoiParams(reacquire_every=0)
    renderer.render(frames[0][0])  # warm-up: GL state, shader compilation
    render_s, encode_s, wall_s, area = [], [], [], []
    for snap, hands in frames:
        windows = None
        if roi:
            by_name, _ = rig_windows(cams, hands, 0.0, 1, params)
            windows = [tuple(by_name[c.name]) for c in cams]
        w0, t0 = time.perf_counter(), time.process_time()  # CPU time: less at the mercy of a busy machine
        images = renderer.render(snap, windows)
        t1 = time.process_time()
        for img in images:
            encode_jpeg(img, 80)
        render_s.append(t1 - t0)
        encode_s.append(time.process_time() - t1)
        wall_s.append(time.perf_counter() - w0)
        area.append(np.mean([img.shape[0] * img.shape[1] for img in images]) / (width * height))
    renderer.close()
    render_ms, encode_ms = 1e3 * np.median(render_s), 1e3 * np.median(encode_s)
    return {"size": f"{width}x{height}", "roi": roi, "render_ms": round(float(render_ms), 1),
            "encode_ms": round(float(encode_ms), 1), "wall_ms": round(float(1e3 * np.median(wall_s)), 1),
            "pixels_read_fraction": round(float(np.mean(area)), 3),
            "max_rate_hz_one_core": round(1e3 / (render_ms + encode_ms), 1)}


def write_pngs(folder: Path, seed: int = 1, t: float = 3.0, view: int = 1) -> None:
    """docs images: one camera's 640x480 view mid-demonstration, and all seven views with the
    windows camhub reads out around the hands."""
    import cv2  # only for the documentation images

    sim = WorldSim("assembly", seed=seed)
    sim.step(int(t / sim.physics_dt))
    snap = snapshot(sim.task, sim.data, sim.robot_name, seed, sim.demo, sim.teacher.tactile_hand)
    renderer = SceneRenderer("assembly", 640, 480)
    images = renderer.render(snap)
    cams = [CameraGeometry(c.name, 640, 480, c.K, np.zeros(5), c.world_T_cam) for c in renderer.cameras]
    windows, _ = rig_windows(cams, sim.hand_keypoints().reshape(-1, 3), 0.0, 1, RoiParams(reacquire_every=0))
    renderer.close()
    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / "camera_view.png"), cv2.cvtColor(images[view], cv2.COLOR_RGB2BGR))
    tiles = []
    for cam, img in zip(cams, images, strict=True):
        x, y, w, h = windows[cam.name]
        tile = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
        cv2.rectangle(tile, (x, y), (x + w - 1, y + h - 1), (0, 220, 255), 3)
        cv2.putText(tile, f"{cam.name}  window {w}x{h}", (12, 36), cv2.FONT_HERSHEY_SIMPLEX, 1.1, (255, 255, 255), 2)
        tiles.append(cv2.resize(tile, (320, 240), interpolation=cv2.INTER_AREA))
    tiles.append(np.zeros_like(tiles[0]))
    sheet = np.vstack([np.hstack(tiles[i:i + 4]) for i in (0, 4)])
    cv2.imwrite(str(folder / "camera_windows.png"), sheet)
    print(f"wrote {folder / 'camera_view.png'}, {folder / 'camera_windows.png'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20, help="frame sets per configuration")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=".bench/camhub.json")
    parser.add_argument("--png", metavar="DIR", help="write the documentation images to DIR (docs) and stop")
    args = parser.parse_args()
    if args.png:
        write_pngs(Path(args.png))
        return
    frames = states(args.frames, args.seed)
    rows = [measure(w, h, frames, roi) for w, h in SIZES for roi in (False, True)]
    base = rows[0]["render_ms"] + rows[0]["encode_ms"]
    for r in rows:
        r["ratio_vs_256x192_full"] = round((r["render_ms"] + r["encode_ms"]) / base, 2)
    print(f"{'size':>8} {'roi':>5} {'render ms':>10} {'jpeg ms':>8} {'wall ms':>8} {'pixels':>7} {'ratio':>6} "
          f"{'max Hz':>7}")
    for r in rows:
        print(f"{r['size']:>8} {r['roi']!s:>5} {r['render_ms']:>10} {r['encode_ms']:>8} {r['wall_ms']:>8} "
              f"{r['pixels_read_fraction']:>7} {r['ratio_vs_256x192_full']:>6} {r['max_rate_hz_one_core']:>7}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"frame_sets": args.frames, "cameras": 7, "rows": rows,
                               "note": "medians per frame set of 7 cameras, CPU ms of the process (wall ms beside); "
                                       "software OpenGL (llvmpipe, 1 thread)"},
                              indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
