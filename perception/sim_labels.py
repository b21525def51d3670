"""``xm detector label``: the simulator's stand-in for hand-made labels. Renders camera windows
of the simulated rig (services/world/render.py) at states of scripted demonstrations (several
seeds, so several layouts, teachers' looks and lightings), projects the truth into each window and
writes the labelled set as COCO keypoints JSON + PNG images (perception/labels.py), the same format
a person labelling real camera images produces.

Windows are the ones camhub reads (services/camhub/roi.py) around the true hands; every
``full_every``-th frame set is read in full, as camhub's reacquisition does. Visibility: 0 outside
the window, behind the camera or the hand parked off the cell; 1 occluded (perception/occlusion.py);
2 visible.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from perception.labels import Frame, keypoint_names, write_coco
from perception.occlusion import HAND_CLEARANCE_M, OBJECT_CLEARANCE_M, hidden_by_capsules, hidden_by_geoms
from services.camhub.roi import CameraGeometry, RoiParams, project, rig_windows
from services.world.appearance import session_look, teacher_capsules
from services.world.render import SceneRenderer, snapshot
from services.world.sim import WorldSim
from shared.demo import HAND_NAMES

MAX_FRAMES = 200  # the labelling budget: one frame is one camera's window image
PARKED_Z = -0.5  # hands below this are parked off the cell and drawn nowhere


def frame_sets(task: str, seeds: list[int], per_seed: int, demos: int, rng: np.random.Generator):
    """Yields (sim, seed) at ``per_seed`` random times spread over the first ``demos`` demonstrations
    of each seed."""
    for seed in seeds:
        sim = WorldSim(task, seed=seed)
        for d in range(demos):
            sim.start_demo(d)
            n = per_seed // demos + (1 if d < per_seed % demos else 0)
            times = np.sort(rng.uniform(0.0, sim.teacher.duration, n))
            for t in times:
                steps = int(round((t - sim.demo_time()) / sim.physics_dt))
                if steps > 0:
                    sim.step(steps)
                yield sim, seed


def label_frame_set(renderer: SceneRenderer, sim: WorldSim, seed: int, full: bool) -> list[tuple[np.ndarray, Frame]]:
    snap = snapshot(sim.task, sim.data, sim.robot_name, seed, sim.demo, sim.teacher.tactile_hand)
    hands = sim.hand_keypoints()
    _, objects = sim.object_keypoints()
    cams = [CameraGeometry(c.name, renderer.width, renderer.height, c.K, np.zeros(5), c.world_T_cam)
            for c in renderer.cameras]
    present = np.repeat(~np.all(hands[..., 2] < PARKED_Z, axis=1), hands.shape[1])
    points = np.concatenate([hands.reshape(-1, 3), objects])
    exists = np.concatenate([present, np.ones(len(objects), bool)])
    windows, _ = rig_windows(cams, None if full else hands.reshape(-1, 3)[present], 0.0, 1,
                             RoiParams(reacquire_every=0))
    images = renderer.render(snap, [tuple(windows[c.name]) for c in cams])
    capsules = teacher_capsules(hands, HAND_NAMES, snap.glove_hand, session_look(seed, snap.demo))
    n_hand = hands.reshape(-1, 3).shape[0]
    clearance = np.r_[np.full(n_hand, HAND_CLEARANCE_M), np.full(len(objects), OBJECT_CLEARANCE_M)]
    m = renderer.model
    skip = {m.body(f"{h}_kp{k}").id for h in HAND_NAMES for k in range(21)}
    out = []
    for cam, img in zip(cams, images, strict=True):
        x0, y0, w, h = windows[cam.name]
        uv, depth = project(points, cam.K, cam.dist, cam.world_T_cam)
        local = uv - [x0, y0]
        inside = (depth > 0.05) & (local[:, 0] >= -0.5) & (local[:, 0] <= w - 0.5) & (local[:, 1] >= -0.5) & \
                 (local[:, 1] <= h - 0.5) & exists
        eye = cam.world_T_cam[:3, 3]
        hidden = hidden_by_capsules(eye, points, clearance, capsules)
        hidden |= hidden_by_geoms(m, renderer.data, eye, points, clearance, skip)
        vis = np.where(inside, np.where(hidden, 1, 2), 0).astype(np.uint8)
        out.append((img, Frame("", cam.name, (int(x0), int(y0), int(w), int(h)), (cam.width, cam.height), local, vis,
                               {"seed": seed, "demo": int(sim.demo), "time": round(sim.demo_time(), 3)})))
    return out


def make_set(out: Path, task: str, seeds: list[int], frames: int, width: int, height: int, full_every: int,
             description: str, rng_seed: int = 0) -> int:
    """Renders and writes one labelled set of at most ``frames`` window images; returns how many."""
    rng = np.random.default_rng(rng_seed)
    renderer = SceneRenderer(task, width, height)
    n_cams = len(renderer.cameras)
    n_sets = max(1, frames // n_cams)
    per_seed = max(1, int(np.ceil(n_sets / len(seeds))))
    (out / "images").mkdir(parents=True, exist_ok=True)
    written: list[Frame] = []
    bar = tqdm(total=n_sets * n_cams, desc=f"label {out.name}", unit="img")
    try:
        for i, (sim, seed) in enumerate(frame_sets(task, seeds, per_seed, 2, rng)):
            if len(written) + n_cams > frames:
                break
            for img, fr in label_frame_set(renderer, sim, seed, full_every > 0 and i % full_every == 0):
                fr.file_name = f"images/{len(written):04d}_{fr.camera}.png"
                cv2.imwrite(str(out / fr.file_name), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
                written.append(fr)
                bar.update(1)
    finally:
        bar.close()
        renderer.close()
    write_coco(out / "labels.json", task, written, description)
    return len(written)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="xm detector label", description=__doc__.splitlines()[0])
    p.add_argument("--out", default="runs/detector/labels", help="folder for train/ and eval/ sets")
    p.add_argument("--task", default="assembly")
    p.add_argument("--frames", type=int, default=MAX_FRAMES, help=f"training images (at most {MAX_FRAMES})")
    p.add_argument("--eval-frames", type=int, default=70, help="held-out images (other seeds)")
    p.add_argument("--seeds", default="1,2,3,4,5,6,7", help="training seeds (layouts, looks, lighting)")
    p.add_argument("--eval-seeds", default="101,102,103", help="held-out seeds")
    p.add_argument("--size", default="256x192", help="full image size (the live rig's)")
    p.add_argument("--full-every", type=int, default=4, help="every n-th frame set as full frames (0: never)")
    a = p.parse_args(argv)
    if a.frames > MAX_FRAMES:
        p.error(f"--frames: at most {MAX_FRAMES} (the labelling budget)")
    width, height = (int(v) for v in a.size.split("x"))
    names = keypoint_names(a.task)
    for name, seeds, frames in (("train", a.seeds, a.frames), ("eval", a.eval_seeds, a.eval_frames)):
        if frames <= 0:
            continue
        folder = Path(a.out) / name
        n = make_set(folder, a.task, [int(s) for s in seeds.split(",")], frames, width, height, a.full_every,
                     f"simulated stand-in for hand labels ({name}, seeds {seeds})",
                     rng_seed=0 if name == "train" else 1)
        print(f"{folder}/labels.json: {n} window images, {len(names)} keypoints each")
    return 0
