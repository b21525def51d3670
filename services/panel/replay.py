"""Review of a recorded demonstration (pure: files and arrays, no viser, no Zenoh).

``load_timeline`` reads a recording once (a worker thread's job: it decodes every message the
review draws) into per-stream time series; ``Timeline.frame(t)`` gives the newest message of each
stream at or before ``t``, keyed as the panel's live state is (``scene``, ``tactile/left``,
``image/cam0``, ...), so the live drawing code draws a replayed frame unchanged. Camera images
stay in the file (``ImageRef``) and are read when shown, so a long recording does not fill memory. ``Playhead`` is
the scrubber's state (position, play, speed, step), the marks say where the hands' keypoints were
unobserved and where a glove lost frames, and ``timeline_strip`` / ``camera_grid`` draw them.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from mcap.reader import SeekingReader

from services.recorder.writer import is_complete, read_segment, recording_files
from shared import msgs
from shared.keys import CAMERAS

TACTILE_KEEP_HZ = 30.0  # decoded heatmaps kept for review (the glove sends 100 Hz; sequence numbers all kept)
MESH_KEEP_HZ = 5.0  # tactile meshes are large; the live panel draws them at 5 Hz too
GLOVE_GAP_PERIODS = 3.0  # a glove silent this many median periods counts as a gap, even without a sequence jump
MIN_SILENCE_S = 0.2  # shorter silences are receive jitter on a busy host, not lost frames
STREAMS = {  # (service, topic) of a key xm/<service>/<instance>/<topic> -> its stream name in a frame
    ("recon", "scene"): "scene", ("recon", "tactile_mesh"): "tactile_mesh", ("policy", "plan"): "plan",
    ("trajopt", "trajectory"): "trajectory",
    ("world", "session"): "session", ("robot", "state"): "state", ("glove", "tactile"): "tactile/{instance}",
    ("camhub", "image"): "image/{instance}", ("camhub", "info"): "info/{instance}",
}


class ReplayError(ValueError):
    """A recording with nothing to review."""


def stream_of(key: str) -> str | None:
    """The frame name of a recorded key (``xm/glove/left/tactile`` -> ``tactile/left``), or None."""
    chunks = key.split("/")
    if len(chunks) != 4 or chunks[0] != "xm":
        return None
    name = STREAMS.get((chunks[1], chunks[3]))
    return None if name is None else name.format(instance=chunks[2])


@dataclass
class Series:
    times: list[float] = field(default_factory=list)  # seconds from the recording's start
    items: list[Any] = field(default_factory=list)  # decoded messages; images of indexed segments: ImageRef

    def at(self, t: float) -> Any:
        i = bisect.bisect_right(self.times, t) - 1
        return self.items[i] if i >= 0 else None


@dataclass
class GloveGap:
    hand: str
    t: float  # seconds from start, the frame after the gap
    lost: int  # frames missing by the sequence counter (0: a silence without a counter jump)
    seconds: float


@dataclass
class Timeline:
    duration: float
    series: dict[str, Series]
    scene_times: np.ndarray  # (S,)
    unobserved: np.ndarray  # (S,) fraction of hand keypoints unobserved in each scene
    gaps: list[GloveGap]
    skipped: dict[str, int]  # messages that did not decode, per key
    cut: list[str]  # where a cut segment ended

    def frame(self, t: float) -> dict[str, Any]:
        """The newest message of each stream at or before ``t`` (streams without one are left out)."""
        out = {}
        for name, s in self.series.items():
            item = s.at(t)
            if item is not None:
                out[name] = item
        return out

    def step_times(self) -> list[float]:
        """Where a single step lands: the scene times, or every stream's when there is no scene."""
        if len(self.scene_times):
            return self.scene_times.tolist()
        return sorted({t for s in self.series.values() for t in s.times})

    def lost_frames(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for g in self.gaps:
            out[g.hand] = out.get(g.hand, 0) + g.lost
        return out


def unobserved_fraction(hand_mask: Sequence[int], hands: int) -> float:
    """Share of the hand keypoints a scene marks unobserved (an empty mask: all observed)."""
    mask = np.asarray(hand_mask, np.uint8)
    if hands == 0 or mask.size == 0:
        return 0.0
    return float(1.0 - mask.mean())


def glove_gaps(hand: str, times: Sequence[float], sequences: Sequence[int],
               periods: float = GLOVE_GAP_PERIODS, min_silence: float = MIN_SILENCE_S) -> list[GloveGap]:
    """Frames a glove lost: jumps of its sequence counter (modulo 2^32), and silences longer than
    ``periods`` median periods and ``min_silence`` seconds."""
    t = np.asarray(times, float)
    if len(t) < 2:
        return []
    seq = np.asarray(sequences, np.int64)
    jump = (np.diff(seq) % (1 << 32)) - 1
    dt = np.diff(t)
    period = float(np.median(dt)) if len(dt) else 0.0
    silent = dt > max(periods * period, min_silence)
    out = []
    for i in np.flatnonzero((jump > 0) | silent):
        out.append(GloveGap(hand, float(t[i + 1]), int(max(jump[i], 0)), float(dt[i])))
    return out


@dataclass(frozen=True)
class ImageRef:
    """A recorded camera image left in its (complete, indexed) segment: read when shown."""
    segment: Path
    key: str
    log_time: int


def build_timeline(stored: Iterable[tuple[Any, Path | None]], cut: list[str] | None = None) -> Timeline:
    """Timeline of recorded messages (``services.recorder.writer.Stored``), each with the complete
    segment holding it (its images are then read when shown) or None (kept in memory). Streaming:
    only what the review keeps is held, never the whole recording."""
    series: dict[str, Series] = {}
    skipped: dict[str, int] = {}
    sequences: dict[str, tuple[list[int], list[int]]] = {}  # hand -> (log times, sequence numbers)
    span = [None, None]
    for m, segment in stored:
        name = stream_of(m.key)
        if name is None:
            continue
        span[0] = m.log_time if span[0] is None else min(span[0], m.log_time)
        span[1] = m.log_time if span[1] is None else max(span[1], m.log_time)
        s = series.setdefault(name, Series())
        if name.startswith("image/") and segment is not None:
            s.times.append(m.log_time)
            s.items.append(ImageRef(segment, m.key, m.log_time))
            continue
        if name == "tactile_mesh" and s.times and m.log_time - s.times[-1] < 1e9 / MESH_KEEP_HZ:
            continue
        try:
            msg = msgs.deserialize(m.data, m.msgtype)
        except msgs.MessageError:
            skipped[m.key] = skipped.get(m.key, 0) + 1
            continue
        if name.startswith("tactile/"):
            times, seqs = sequences.setdefault(name.split("/", 1)[1], ([], []))
            times.append(m.log_time)
            seqs.append(int(msg.sequence))
            if s.times and m.log_time - s.times[-1] < 1e9 / TACTILE_KEEP_HZ:
                continue
        s.times.append(m.log_time)
        s.items.append(msg)
    if span[0] is None:
        raise ReplayError("no message the review can draw (scene, robot state, gloves, cameras, plan, session)")
    t0 = span[0]
    for s in series.values():  # seconds from the start, in time order (a cut segment may be slightly out of it)
        order = np.argsort(np.asarray(s.times, np.int64), kind="stable")
        s.times = ((np.asarray(s.times, np.int64)[order] - t0) * 1e-9).tolist()
        s.items = [s.items[i] for i in order]
    gaps = []
    for hand, (times, seqs) in sequences.items():
        order = np.argsort(np.asarray(times, np.int64), kind="stable")
        gaps += glove_gaps(hand, (np.asarray(times, np.int64)[order] - t0) * 1e-9, np.asarray(seqs)[order])
    scenes = series.get("scene", Series())
    unobserved = [unobserved_fraction(m.hand_mask, len(m.hand_names)) for m in scenes.items]
    return Timeline((span[1] - t0) * 1e-9, {k: v for k, v in series.items() if v.times},
                    np.asarray(scenes.times), np.asarray(unobserved), sorted(gaps, key=lambda g: g.t), skipped,
                    list(cut or []))


def load_timeline(recording: str | Path) -> Timeline:
    """Read a whole recording (complete or cut) into a Timeline: slow, run it off the event loop."""
    cut: list[str] = []

    def stored() -> Iterator[tuple[Any, Path | None]]:
        for seg in recording_files(recording):
            indexed = seg if is_complete(seg) else None
            for m in read_segment(seg, cut=cut):
                yield m, indexed

    return build_timeline(stored(), cut)


def image_bytes(items: dict[str, Any]) -> dict[str, bytes]:
    """JPEG bytes of replayed images by camera: ``ImageRef`` read from its segment (one indexed read
    per segment for all cameras), messages kept in memory as they are. OSError / ValueError when a
    segment is gone or damaged."""
    out: dict[str, bytes] = {}
    wanted: dict[Path, dict[str, tuple[str, int]]] = {}
    for cam, item in items.items():
        if isinstance(item, ImageRef):
            wanted.setdefault(item.segment, {})[item.key] = (cam, item.log_time)
        else:
            out[cam] = bytes(item.data)
    for segment, keys in wanted.items():
        times = [t for _, t in keys.values()]
        with segment.open("rb") as f:
            for schema, channel, message in SeekingReader(f).iter_messages(
                    topics=list(keys), starting_at=min(times), ending_at=max(times)):
                cam, log_time = keys[channel.topic]
                if message.log_time == log_time and schema is not None:
                    out[cam] = bytes(msgs.deserialize(message.data, schema.name).data)
    return out


@dataclass
class Playhead:
    """The scrubber: position within [start, end] (the trim window), play/pause, speed, steps."""
    start: float
    end: float
    position: float = 0.0
    playing: bool = False
    speed: float = 1.0

    def __post_init__(self) -> None:
        self.position = self.clamp(self.position)

    def clamp(self, t: float) -> float:
        return float(min(max(t, self.start), self.end))

    def seek(self, t: float) -> float:
        self.position = self.clamp(t)
        return self.position

    def advance(self, dt: float) -> float:
        """Move by ``dt`` wall seconds at ``speed`` while playing; stops at the end."""
        if self.playing:
            self.seek(self.position + dt * self.speed)
            if self.position >= self.end:
                self.playing = False
        return self.position

    def step(self, times: Sequence[float], direction: int) -> float:
        """To the next (+1) or previous (-1) of ``times`` within the window; pauses."""
        self.playing = False
        if not len(times):
            return self.position
        if direction > 0:
            i = bisect.bisect_right(times, self.position + 1e-9)
            target = times[i] if i < len(times) else self.end
        else:
            i = bisect.bisect_left(times, self.position - 1e-9) - 1
            target = times[i] if i >= 0 else self.start
        return self.seek(target)


# --- drawing --------------------------------------------------------------------------------------
STRIP_BG = np.array((235, 235, 235), np.uint8)
UNOBSERVED_RGB = np.array((220, 40, 40), float)
GAP_RGB = (255, 150, 0)
CURSOR_RGB = (20, 20, 20)
TRIMMED_RGB = np.array((150, 150, 150), float)


def timeline_strip(timeline: Timeline, cursor: float, window: tuple[float, float] | None = None,
                   width: int = 480, height: int = 28) -> np.ndarray:
    """(height, width, 3) uint8: the upper half shaded red by the share of unobserved hand keypoints,
    orange ticks in the lower half where a glove lost frames, the trimmed-off parts greyed, the
    cursor as a black line."""
    img = np.broadcast_to(STRIP_BG, (height, width, 3)).copy()
    span = max(timeline.duration, 1e-9)

    def col(t: float) -> int:
        return int(np.clip(round(t / span * (width - 1)), 0, width - 1))

    if len(timeline.scene_times):
        cols = np.clip(np.round(timeline.scene_times / span * (width - 1)).astype(int), 0, width - 1)
        share = np.zeros(width)
        np.maximum.at(share, cols, timeline.unobserved)
        edges = np.searchsorted(cols, np.arange(width), side="right") - 1  # each column: the last scene before it
        share = np.where(edges >= 0, share[cols[np.clip(edges, 0, None)]], 0.0)
        top = (1 - share[:, None]) * STRIP_BG + share[:, None] * UNOBSERVED_RGB
        img[: height // 2] = top.round().astype(np.uint8)[None]
    for g in timeline.gaps:
        c = col(g.t)
        img[height // 2:, max(0, c - 1):c + 2] = GAP_RGB
    if window is not None:
        lo, hi = col(window[0]), col(window[1])
        for a, b in ((0, lo), (hi + 1, width)):
            if b > a:
                img[:, a:b] = (img[:, a:b] * 0.4 + TRIMMED_RGB * 0.6).round().astype(np.uint8)
    c = col(cursor)
    img[:, max(0, c - 1):c + 1] = CURSOR_RGB
    return img


def decode_jpeg(data: bytes) -> np.ndarray | None:
    """RGB image of a JPEG, None when it does not decode."""
    bgr = cv2.imdecode(np.frombuffer(bytes(data), np.uint8), cv2.IMREAD_COLOR)
    return None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def camera_grid(images: dict[str, np.ndarray | None], cameras: Sequence[str] = CAMERAS,
                tile: tuple[int, int] = (160, 120), columns: int = 3) -> np.ndarray:
    """One image of every camera, ``columns`` per row, each labelled; a camera without an image is grey."""
    w, h = tile
    rows = -(-len(cameras) // columns)
    out = np.full((rows * h, columns * w, 3), 60, np.uint8)
    for i, cam in enumerate(cameras):
        r, c = divmod(i, columns)
        img = images.get(cam)
        cell = out[r * h:(r + 1) * h, c * w:(c + 1) * w]
        if img is not None:
            cell[:] = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        cv2.putText(cell, cam, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 0), 1, cv2.LINE_AA)
    return out


def marks_text(timeline: Timeline) -> str:
    """One line on what the marks show: unobserved keypoints and frames each glove lost."""
    worst = float(timeline.unobserved.max()) if len(timeline.unobserved) else 0.0
    seen = (f"keypoints unobserved in {int((timeline.unobserved > 0).sum())} of {len(timeline.unobserved)} "
            f"scenes (at most {worst:.0%})") if len(timeline.unobserved) else "no scene messages"
    lost = timeline.lost_frames()
    gloves = ", ".join(f"{h} glove lost {n} frames in {sum(g.hand == h for g in timeline.gaps)} gaps"
                       for h, n in sorted(lost.items())) or "no glove gaps"
    extra = f"; {sum(timeline.skipped.values())} messages did not decode" if timeline.skipped else ""
    cut = "; cut by a crash: " + "; ".join(timeline.cut) if timeline.cut else ""
    return f"{seen}; {gloves}{extra}{cut}"


def signals(timeline: Timeline, points: int = 300) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Signals to plot over the recording, held between messages on ``points`` evenly spaced times:
    the share of unobserved hand keypoints (%) and each glove's mean pressure (kPa)."""
    t = np.linspace(0.0, max(timeline.duration, 1e-3), points)
    out: dict[str, np.ndarray] = {}
    if len(timeline.scene_times):
        i = np.clip(np.searchsorted(timeline.scene_times, t, side="right") - 1, 0, None)
        out["keypoints unobserved %"] = 100.0 * timeline.unobserved[i]
    for name, s in sorted(timeline.series.items()):
        if name.startswith("tactile/"):
            mean = np.array([float(np.mean(m.pressure)) if len(m.pressure) else 0.0 for m in s.items])
            i = np.clip(np.searchsorted(np.asarray(s.times), t, side="right") - 1, 0, None)
            out[f"{name.split('/', 1)[1]} glove kPa"] = mean[i]
    return t, out
