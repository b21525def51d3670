"""Getting frame sets for a calibration: from the running world (its board sequence rendered at the
calibration size), from camhub's image keys (the live rig), from the world model alone (no running
deployment: benches and tests), or from a folder of saved frames.

Each frame set is handed to ``sink(index, images)`` as soon as it exists, so detection keeps up
with capture and no run holds hundreds of full-size images in memory.
"""

from __future__ import annotations

import json
import queue
import re
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from calibration.board import Settings
from services.world import calibration_sequence as calseq
from services.world.model import CALIB_BOARD, camera_specs
from services.world.render import SceneRenderer, Snapshot
from shared import msgs

WORLD_CMD = "xm/world/sim/@cmd/calibration"
SNAPSHOT_KEY = "xm/world/sim/@snapshot"
CAMHUB_IMAGES = "xm/camhub/*/image"

Sink = Callable[[int, list[np.ndarray]], None]


class CaptureError(RuntimeError):
    """No frames: the world or camhub did not answer, or answered something unusable."""


def query(session, key: str, request: dict | None = None, timeout: float = 3.0) -> dict | bytes:
    replies = list(session.get(key, payload=json.dumps(request) if request is not None else None, timeout=timeout))
    ok = [r.ok for r in replies if r.ok is not None]
    if not ok:
        raise CaptureError(f"no answer from {key} within {timeout} s (is `xm up deploy/sim.toml` running?)")
    data = ok[0].payload.to_bytes()
    return json.loads(data) if request is not None else data


def world_pose(session, settings: Settings, index: int, seed: int) -> dict:
    reply = query(session, WORLD_CMD, {"index": index, "count": settings.frames, "seed": seed,
                                       "registration": settings.registration.to_dict()})
    if not reply.get("ok"):
        raise CaptureError(f"world refused pose {index}: {reply.get('error')}")
    if reply["board"] != settings.board.to_dict():
        raise CaptureError(f"the simulated board {reply['board']} differs from the deployment's [calibration] board "
                           f"{settings.board.to_dict()}: make them equal")
    return reply


def hide_board(session) -> None:
    try:
        query(session, WORLD_CMD, {"hide": True})
    except CaptureError:
        pass  # the world is gone: nothing left to hide


def from_world(session, settings: Settings, seed: int, sink: Sink, progress: Callable[[int], None]) -> list[str]:
    """Drive the world's sequence; render each pose from the world's snapshot at the calibration size."""
    renderer = None
    try:
        for i in range(settings.frames):
            world_pose(session, settings, i, seed)
            snap = Snapshot.from_json(query(session, SNAPSHOT_KEY))
            if renderer is None:
                renderer = SceneRenderer(snap.task, settings.width, settings.height, robot=snap.robot)
            sink(i, renderer.render(snap))
            progress(i)
    finally:
        hide_board(session)
        if renderer is not None:
            renderer.close()
    return [c.name for c in camera_specs(settings.width, settings.height)]


def from_model(settings: Settings, seed: int, sink: Sink, progress: Callable[[int], None],
               task: str = "assembly") -> list[str]:
    """The world's sequence rendered from the model alone: objects at rest, hands out of view."""
    renderer = SceneRenderer(task, settings.width, settings.height)
    try:
        m, d = renderer.model, renderer.data
        mocap = int(m.body_mocapid[m.body(CALIB_BOARD).id])
        for i, pose in enumerate(calseq.sequence(settings.board, settings.frames, seed, settings.registration)):
            pos, quat = calseq.mocap(pose)
            d.mocap_pos[mocap], d.mocap_quat[mocap] = pos, quat
            sink(i, renderer.render(Snapshot(task, 0.0, d.qpos.copy(), d.mocap_pos.copy(), d.mocap_quat.copy())))
            progress(i)
    finally:
        renderer.close()
    return [c.name for c in renderer.cameras]


class CamhubFrames:
    """Complete frame sets (one image per camera, same trigger stamp) from camhub's image keys."""

    def __init__(self, session) -> None:
        self._q: queue.Queue = queue.Queue()
        self._sub = session.declare_subscriber(CAMHUB_IMAGES, self._on_image)
        self._partial: dict[float, dict[str, np.ndarray]] = {}
        self.names: list[str] = []

    def _on_image(self, sample) -> None:
        name = str(sample.key_expr).split("/")[2]
        self._q.put((name, sample.payload.to_bytes()))

    def next_set(self, after: float, timeout: float = 10.0, settle_s: float = 0.3) -> tuple[float, dict]:
        """The first complete frame set stamped at or after ``after``; names are those seen in ``settle_s``."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                name, data = self._q.get(timeout=0.2)
            except queue.Empty:
                continue
            msg = msgs.deserialize(data, "sensor_msgs/msg/CompressedImage")
            stamp = msgs.stamp_seconds(msg.header.stamp)
            if name not in self.names:
                self.names.append(name)
                self.names.sort(key=_natural)
                deadline = max(deadline, time.monotonic() + settle_s)
            if stamp < after:
                continue
            bgr = cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_COLOR)
            frames = self._partial.setdefault(stamp, {})
            frames[name] = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            if len(frames) == len(self.names) and len(self.names) > 0:
                self._partial = {s: f for s, f in self._partial.items() if s > stamp}
                return stamp, frames
        raise CaptureError(f"no complete frame set on {CAMHUB_IMAGES} within {timeout} s (is camhub running? "
                           f"cameras seen: {', '.join(self.names) or 'none'})")

    def close(self) -> None:
        self._sub.undeclare()


def _natural(name: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def from_camhub_sim(session, settings: Settings, seed: int, sink: Sink, progress: Callable[[int], None]) -> list[str]:
    """Drive the world's sequence and take camhub's first frame set that shows each pose."""
    frames = CamhubFrames(session)
    try:
        for i in range(settings.frames):
            reply = world_pose(session, settings, i, seed)
            _, images = frames.next_set(after=float(reply["time"]) + 1e-6)
            sink(i, [images[n] for n in frames.names])
            progress(i)
    finally:
        hide_board(session)
        frames.close()
    return frames.names


def record(session, duration_s: float, every_s: float, sink: Sink, progress: Callable[[int], None],
           prompt: Callable[[str], None]) -> list[str]:
    """Hardware: frame set 0 is the board lying at its registration place, then frame sets every
    ``every_s`` while a person waves the board through the working volume for ``duration_s``."""
    frames = CamhubFrames(session)
    try:
        prompt("lay the board flat at its registration place on the table (the deployment's [calibration] "
               "registration), step back and press Enter")
        _, images = frames.next_set(after=0.0)
        sink(0, [images[n] for n in frames.names])
        prompt(f"now wave the board through the working volume for {duration_s:.0f} s: tilt it towards every "
               "camera, near and far, into the image corners; press Enter to start")
        t_end, i = time.monotonic() + duration_s, 1
        stamp = 0.0
        while time.monotonic() < t_end:
            stamp, images = frames.next_set(after=stamp + every_s if stamp else 0.0)
            sink(i, [images[n] for n in frames.names])
            progress(i)
            i += 1
    finally:
        frames.close()
    return frames.names


def save_frames(directory: Path, index: int, names: list[str], images: list[np.ndarray]) -> None:
    folder = directory / f"{index:04d}"
    folder.mkdir(parents=True, exist_ok=True)
    for name, img in zip(names, images, strict=True):
        cv2.imwrite(str(folder / f"{name}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if img.ndim == 3 else img)


def from_folder(directory: Path, sink: Sink, progress: Callable[[int], None]) -> list[str]:
    """Frame sets saved as ``DIR/<frame set>/<camera>.png`` (frame set 0: the registration)."""
    sets = sorted(p for p in Path(directory).iterdir() if p.is_dir())
    if not sets:
        raise CaptureError(f"{directory}: no frame-set folders (expected {directory}/0000/cam0.png ...)")
    names = sorted({f.stem for s in sets for f in s.glob("*.png")}, key=_natural)
    for i, folder in enumerate(sets):
        images = []
        for name in names:
            img = cv2.imread(str(folder / f"{name}.png"), cv2.IMREAD_GRAYSCALE)
            images.append(img)
        sink(i, images)
        progress(i)
    return names
