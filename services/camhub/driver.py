"""Camera rigs: one interface, three sources.

``SimRig`` renders every camera from a state snapshot of the world (MuJoCo, software OpenGL),
reading out only each camera's window. ``DeviceRig`` triggers a set of per-camera sources that
deliver whole frames and crops the windows: ``V4L2Source`` (a video device through OpenCV) and
``FileSource`` (a video file or an image folder, for a recorded session and for tests). A camera
that fails is reported missing and reopened with back-off while the others keep delivering.

Every rig answers ``trigger(windows, now)`` with one ``FrameSet``: one stamp for all cameras and,
per camera, the window image or nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from services.camhub.reopen import CameraState
from services.camhub.roi import Roi, crop, full_frame

SNAPSHOT_KEY = "xm/world/sim/@snapshot"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm")


class RigError(RuntimeError):
    """The rig delivered no frames (world not running, every device missing)."""


class SourceError(RuntimeError):
    """One camera's source cannot open or read; the rig reports it and reopens later."""


class SizeMismatchError(SourceError):
    """A source delivers another resolution than the deployment (and its calibration) says."""


@dataclass
class CameraFrame:
    name: str
    roi: Roi  # the window this image shows, in full-image pixels
    image: np.ndarray  # (roi.height, roi.width, 3) uint8 RGB


@dataclass
class FrameSet:
    stamp: float  # one trigger stamp for every camera
    frames: list[CameraFrame]
    missing: list[str] = field(default_factory=list)


class SimRig:
    """The simulated hub. Call ``trigger`` from one and the same worker thread (the GL context lives there)."""

    def __init__(self, session, names: list[str], width: int, height: int, timeout_s: float = 1.0,
                 renderer: object | None = None) -> None:
        self._session = session
        self._timeout = timeout_s
        self._size = (width, height)
        self._names = list(names)
        self._renderer = renderer  # one built ahead (``warm_renderer``, a standby spare), else at the first frame

    def trigger(self, windows: dict[str, Roi], now: float) -> FrameSet:
        from services.world.render import SceneRenderer, Snapshot  # MuJoCo + GL: only the sim source needs them

        replies = list(self._session.get(SNAPSHOT_KEY, timeout=self._timeout))
        ok = [r.ok for r in replies if r.ok is not None]
        if not ok:
            raise RigError(f"no answer from {SNAPSHOT_KEY} within {self._timeout}s (is the world running?)")
        snap = Snapshot.from_json(ok[0].payload.to_bytes())
        if self._renderer is None or (self._renderer.task, self._renderer.robot) != (snap.task, snap.robot):
            if self._renderer is not None:
                self._renderer.close()
            self._renderer = SceneRenderer(snap.task, *self._size, robot=snap.robot)
        cams = [c.name for c in self._renderer.cameras]
        if cams != self._names:
            raise RigError(f"the world's cameras are {cams}, the rig expects {self._names}")
        full = full_frame(*self._size)
        rois = [windows.get(n, full) for n in cams]
        images = self._renderer.render(snap, [tuple(r) for r in rois])
        return FrameSet(snap.time, [CameraFrame(n, r, img) for n, r, img in zip(cams, rois, images, strict=True)])

    def health(self) -> dict:
        return {}

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()


def warm_renderer(task: str, width: int, height: int, robot: str) -> object:
    """A SceneRenderer that has drawn one frame (GL context, shaders, textures: ~0.7 s of a first
    frame, more on a busy host); build it on the thread that will render with it."""
    from services.world.render import SceneRenderer, snapshot  # MuJoCo + GL: only the sim source needs them

    renderer = SceneRenderer(task, width, height, robot=robot)
    renderer.render(snapshot(task, renderer.data, robot))
    return renderer


class V4L2Source:
    """A video device through OpenCV's V4L2 backend at the deployment's resolution and frame rate."""

    def __init__(self, device: str, width: int, height: int, fps: float) -> None:
        self.where = device
        self._size, self._fps = (width, height), fps
        self._cap: cv2.VideoCapture | None = None

    def open(self) -> None:
        index = int(self.where) if self.where.isdigit() else self.where
        cap = cv2.VideoCapture(index, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise SourceError(f"cannot open video device {self.where}")
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self._size[0])
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self._size[1])
        if self._fps > 0:
            cap.set(cv2.CAP_PROP_FPS, self._fps)
        # A device that stays present but stops streaming must not stall the other cameras for
        # OpenCV's default 10 s select() timeout: give up after a few frame periods.
        cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, max(200.0, 3000.0 / self._fps) if self._fps > 0 else 1000.0)
        got = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        if got != self._size:
            cap.release()
            raise SizeMismatchError(f"{self.where} delivers {got[0]}x{got[1]}, the deployment asks for "
                                    f"{self._size[0]}x{self._size[1]}")
        self._cap = cap

    def grab(self, index: int) -> None:
        if self._cap is None or not self._cap.grab():
            raise SourceError(f"{self.where}: no frame (device gone?)")

    def retrieve(self) -> np.ndarray:
        ok, bgr = self._cap.retrieve() if self._cap is not None else (False, None)
        if not ok or bgr is None:
            raise SourceError(f"{self.where}: frame could not be decoded")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class FileSource:
    """One camera of a recorded session: a video file, or a folder of images in name order.

    Frame ``index`` of the rig's frame sets is frame ``index`` of the file (modulo its length when
    looping), so cameras stay aligned even after one of them was missing for a while."""

    def __init__(self, path: str, width: int, height: int, loop: bool = True) -> None:
        self.where = path
        self._size = (width, height)
        self._loop = loop
        self._images: list[Path] = []
        self._video: cv2.VideoCapture | None = None
        self._count = 0
        self._next = 0
        self._frame: np.ndarray | None = None

    def open(self) -> None:
        path = Path(self.where)
        if path.is_dir():
            self._images = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            self._count = len(self._images)
            if not self._count:
                raise SourceError(f"{path}: no images ({', '.join(IMAGE_SUFFIXES)})")
        elif path.is_file():
            video = cv2.VideoCapture(str(path))
            self._count = int(video.get(cv2.CAP_PROP_FRAME_COUNT)) if video.isOpened() else 0
            if self._count <= 0:
                video.release()
                raise SourceError(f"{path}: not a readable video")
            self._video, self._next = video, 0
        else:
            raise SourceError(f"{path}: no such file or folder")

    def frames(self) -> int:
        return self._count

    def grab(self, index: int) -> None:
        if index >= self._count and not self._loop:
            raise SourceError(f"{self.where}: end of recording after {self._count} frames")
        i = index % self._count
        if self._video is not None:
            if i != self._next:
                self._video.set(cv2.CAP_PROP_POS_FRAMES, i)
            ok, bgr = self._video.read()
            self._next = i + 1
        else:
            try:
                bgr = cv2.imread(str(self._images[i]), cv2.IMREAD_COLOR)
            except cv2.error:
                bgr = None
            ok = bgr is not None
        if not ok or bgr is None:
            raise SourceError(f"{self.where}: frame {i} unreadable")
        if (bgr.shape[1], bgr.shape[0]) != self._size:
            raise SizeMismatchError(f"{self.where}: frame {i} is {bgr.shape[1]}x{bgr.shape[0]}, the deployment "
                                    f"asks for {self._size[0]}x{self._size[1]}")
        self._frame = bgr

    def retrieve(self) -> np.ndarray:
        assert self._frame is not None
        return cv2.cvtColor(self._frame, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        if self._video is not None:
            self._video.release()
            self._video = None
        self._images = []


class DeviceRig:
    """Whole-frame sources, one per camera, triggered together; windows are cropped in software.

    ``grab`` on every camera first, then ``retrieve``: the frames are as close in time as the bus
    allows. A camera that fails is closed, reported, and reopened with back-off."""

    def __init__(self, names: list[str], sources: list, width: int, height: int) -> None:
        if len(names) != len(sources):
            raise ValueError(f"{len(sources)} sources for {len(names)} cameras ({', '.join(names)})")
        self._names = list(names)
        self._sources = list(sources)
        self._size = (width, height)
        self.states = [CameraState(n) for n in names]
        self._index = 0

    def open_all(self, now: float) -> list[SourceError]:
        """Open every camera and read its first frame; returns the failures (retried later)."""
        failures = []
        for i in range(len(self._sources)):
            exc = self._open(i, now, probe=True)
            if exc is not None:
                failures.append(exc)
        return failures

    def _open(self, i: int, now: float, probe: bool = False) -> SourceError | None:
        try:
            self._sources[i].open()
            if probe:  # the first frame shows the resolution the source really delivers
                self._sources[i].grab(self._index)
        except (SourceError, OSError, cv2.error) as exc:
            self._sources[i].close()
            err = exc if isinstance(exc, SourceError) else SourceError(f"{self._names[i]}: {exc}")
            self.states[i].failed(now, str(err))
            return err
        self.states[i].opened()
        return None

    def trigger(self, windows: dict[str, Roi], now: float) -> FrameSet:
        index, self._index = self._index, self._index + 1
        live = []
        for i, (source, state) in enumerate(zip(self._sources, self.states, strict=True)):
            if state.due(now):
                self._open(i, now)
            if state.open:
                try:
                    source.grab(index)
                    live.append(i)
                except (SourceError, OSError, cv2.error) as exc:
                    self._lose(i, now, str(exc))
        frames, missing = [], []
        full = full_frame(*self._size)
        for i, name in enumerate(self._names):
            if i in live:
                try:
                    image = self._sources[i].retrieve()
                except (SourceError, OSError, cv2.error) as exc:
                    self._lose(i, now, str(exc))
                else:
                    roi = windows.get(name, full)
                    frames.append(CameraFrame(name, roi, np.ascontiguousarray(crop(image, roi))))
                    self.states[i].delivered()
                    continue
            self.states[i].missed()
            missing.append(name)
        if not frames:
            raise RigError("no camera delivered a frame: " + "; ".join(f"{s.name}: {s.error}" for s in self.states))
        return FrameSet(now, frames, missing)

    def _lose(self, i: int, now: float, error: str) -> None:
        self._sources[i].close()
        self.states[i].failed(now, error)

    def health(self) -> dict:
        return {s.name: s.report() for s in self.states}

    def close(self) -> None:
        for source in self._sources:
            source.close()
