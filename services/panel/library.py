"""The demonstration library: every recording in a directory with its metadata (pure: files only,
no viser, no Zenoh).

A recording is its MCAP segments (``NAME.mcap``, ``NAME.seg0001.mcap``, ...); its teaching metadata
(label, split, outcome, task, teacher, glove hand, start layout, trim) lives beside it in a sidecar
``NAME.demo.json``, so editing a label or a trim never rewrites the recording. What the MCAP itself
says (duration, keys, message counts, the tasks its session messages name, whether it was cut by a
crash) is read from the file: the summary section of closed segments (cheap), a streaming pass
over a cut one. ``Library`` caches that per file size and modification time, so a rescan reads only
new or changed recordings.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from collections import Counter
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from mcap.reader import SeekingReader

from services.recorder.writer import (
    RecordingError,
    check_mcap,
    is_being_written,
    is_complete,
    read_segment,
)
from shared import msgs
from shared.recording_files import recording_segments, segment_key

SPLITS = ("train", "validation", "excluded")
OUTCOMES = ("unknown", "success", "failure")
HANDS = ("left", "right")
SESSION_KEY = "xm/world/sim/session"
SCENE_KEY = "xm/recon/main/scene"
REQUIRED_KEYS = (SCENE_KEY, SESSION_KEY)  # what `xm train` reads from a recording (learning/dataset.py)
SIDECAR_SUFFIX = ".demo.json"


class MetaError(ValueError):
    """Metadata that cannot be stored: an unknown split or outcome, a trim outside the recording."""


@dataclass
class DemoMeta:
    """The teacher's description of one demonstration, stored in its sidecar."""
    label: str = ""
    split: str = "train"
    outcome: str = "unknown"
    task: str = ""
    teacher: str = ""
    glove_hand: str = ""
    layout: str = ""  # the start layout: the world's seed layout (JSON) or the teacher's words
    session: str = ""  # the teaching session it was recorded in
    trim_start_s: float = 0.0  # seconds from the recording's first message
    trim_end_s: float | None = None  # None: to the end
    notes: str = ""

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, data: Any) -> DemoMeta:
        if not isinstance(data, dict):
            raise MetaError(f"metadata is a {type(data).__name__}, not a JSON object")
        known = {f.name for f in fields(cls)}
        meta = cls(**{k: v for k, v in data.items() if k in known})
        meta.check()
        return meta

    def check(self, duration_s: float | None = None) -> None:
        """Raise MetaError unless every field holds an allowed value (trim within ``duration_s`` when given)."""
        for name in ("label", "task", "teacher", "layout", "session", "notes", "glove_hand"):
            if not isinstance(getattr(self, name), str):
                raise MetaError(f"{name} must be text, got {getattr(self, name)!r}")
        if self.split not in SPLITS:
            raise MetaError(f"split {self.split!r} is not one of {', '.join(SPLITS)}")
        if self.outcome not in OUTCOMES:
            raise MetaError(f"outcome {self.outcome!r} is not one of {', '.join(OUTCOMES)}")
        if self.glove_hand not in ("", *HANDS):
            raise MetaError(f"glove_hand {self.glove_hand!r} is not left or right")
        start, end = self.trim_start_s, self.trim_end_s
        if not isinstance(start, (int, float)) or isinstance(start, bool) or start < 0:
            raise MetaError(f"trim_start_s must be a number >= 0, got {start!r}")
        if end is not None and (not isinstance(end, (int, float)) or isinstance(end, bool) or end <= start):
            raise MetaError(f"trim_end_s must be null or a number after trim_start_s ({start}), got {end!r}")
        if duration_s is not None and start >= max(duration_s, 1e-9):
            raise MetaError(f"trim_start_s {start:.2f} s is not before the end of the recording ({duration_s:.2f} s)")

    def window(self, duration_s: float) -> tuple[float, float]:
        """The kept part, seconds from the recording's first message, clipped to the recording."""
        end = duration_s if self.trim_end_s is None else min(self.trim_end_s, duration_s)
        return min(self.trim_start_s, end), end


def sidecar_path(recording: str | Path) -> Path:
    """``NAME.demo.json`` beside ``NAME.mcap`` (the first segment)."""
    path = Path(recording)
    stem = path.name[:-len(".mcap")] if path.name.endswith(".mcap") else path.name
    return path.with_name(stem + SIDECAR_SUFFIX)


def read_meta(recording: str | Path) -> DemoMeta:
    """The sidecar's metadata; defaults when there is none; MetaError when it is unreadable."""
    path = sidecar_path(recording)
    if not path.exists():
        return DemoMeta()
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise MetaError(f"{path.name}: not readable JSON ({exc})") from None
    return DemoMeta.from_json(data)


def write_meta(recording: str | Path, meta: DemoMeta, duration_s: float | None = None) -> Path:
    """Validate and store ``meta`` beside the recording (atomically: a reader never sees half a file)."""
    meta.check(duration_s)
    path = sidecar_path(recording)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(meta.to_json(), f, indent=2, sort_keys=True)
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


@dataclass
class RecordingInfo:
    """What the MCAP segments of one recording hold."""
    segments: list[Path]
    messages: dict[str, int] = field(default_factory=dict)  # per key
    start_ns: int = 0
    end_ns: int = 0
    tasks: list[str] = field(default_factory=list)  # named by its session messages
    cut: list[str] = field(default_factory=list)  # segments without a footer (killed recorder)
    recording_now: bool = False  # a live recorder holds a segment
    error: str = ""  # unreadable

    @property
    def duration_s(self) -> float:
        return max(0.0, (self.end_ns - self.start_ns) * 1e-9)


def _span(info: RecordingInfo, start: int, end: int) -> None:
    info.start_ns = start if not info.start_ns else min(info.start_ns, start)
    info.end_ns = max(info.end_ns, end)


def _session_task(data: bytes, tasks: list[str]) -> None:
    try:
        task = msgs.deserialize(data, "xm_msgs/msg/Session").task
    except msgs.MessageError:
        return
    if task and task not in tasks:
        tasks.append(task)


def read_info(recording: str | Path) -> RecordingInfo:
    """Duration, keys and tasks of the recording whose first segment is ``recording``; never raises:
    an unreadable file is described in ``error``."""
    info = RecordingInfo(recording_segments(recording))
    counts: Counter[str] = Counter()
    try:
        for seg in info.segments:
            check_mcap(seg)
            if is_being_written(seg):  # read once it is closed: a growing file would be re-read every scan
                info.recording_now = True
            elif is_complete(seg):
                with seg.open("rb") as f:
                    reader = SeekingReader(f)
                    summary = reader.get_summary()
                    stats = summary.statistics if summary else None
                    if stats is not None and stats.message_count:
                        _span(info, stats.message_start_time, stats.message_end_time)
                        for cid, n in stats.channel_message_counts.items():
                            counts[summary.channels[cid].topic] += n
                    if counts.get(SESSION_KEY) or any(c.topic == SESSION_KEY for c in summary.channels.values()):
                        for _s, _c, m in reader.iter_messages(topics=[SESSION_KEY]):
                            _session_task(m.data, info.tasks)
            else:  # cut by a crash: a streaming pass up to the last whole chunk
                for m in read_segment(seg):
                    counts[m.key] += 1
                    _span(info, m.log_time, m.log_time)
                    if m.key == SESSION_KEY:
                        _session_task(m.data, info.tasks)
                info.cut.append(seg.name)
    except (RecordingError, OSError, ValueError) as exc:
        info.error = str(exc)
    except Exception as exc:  # mcap raises several unrelated types for damaged files
        info.error = f"{type(exc).__name__}: {exc}"
    info.messages = dict(sorted(counts.items()))
    return info


@dataclass
class Entry:
    """One row of the library: a recording, its metadata and why it cannot be trained on, if so."""
    path: Path  # first segment
    info: RecordingInfo
    meta: DemoMeta
    problems: list[str]

    @property
    def name(self) -> str:
        return self.path.name[:-len(".mcap")]

    @property
    def usable(self) -> bool:
        """Fit for training or validation (its split says which)."""
        return not self.problems

    @property
    def trainable(self) -> bool:
        return self.usable and self.meta.split == "train"


def problems_of(path: Path, info: RecordingInfo, meta_error: str, task: str | None) -> list[str]:
    """Why a recording cannot be learned from, each reason in words a teacher can act on."""
    out = []
    if info.error:
        out.append(f"unreadable: {info.error}")
    if info.recording_now:
        out.append("being recorded")
    for seg in info.cut:
        out.append(f"cut by a crash ({seg} has no footer): `xm record --repair {path.parent / seg}`")
    if not info.error and not info.messages and not info.recording_now:
        out.append("no messages")
    elif not info.error and not info.recording_now:
        missing = [k for k in REQUIRED_KEYS if not info.messages.get(k)]
        if missing:
            out.append(f"missing keys: {', '.join(missing)}")
    if meta_error:
        out.append(f"metadata: {meta_error}")
    if task and info.tasks and task not in info.tasks:
        out.append(f"another task: {', '.join(info.tasks)} (the session's is {task})")
    return out


def recordings(directory: str | Path) -> list[Path]:
    """First segments of the recordings in ``directory``, by name."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    firsts = {}
    for p in directory.glob("*.mcap"):
        base, _index = segment_key(p)
        if p.is_file() and not p.name.startswith("."):
            firsts.setdefault(base, directory / f"{base}.mcap")
    return [firsts[k] for k in sorted(firsts)]


def _signature(path: Path) -> tuple:
    """Changes whenever a segment is added, grows or is rewritten (a repair)."""
    out = []
    for seg in recording_segments(path):
        try:
            st = seg.stat()
        except OSError:
            continue
        out.append((seg.name, st.st_size, st.st_mtime_ns))
    return tuple(out)


class Library:
    """The recordings of one directory; ``scan`` re-reads only recordings whose files changed."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        self._info: dict[Path, tuple[tuple, RecordingInfo]] = {}

    def info(self, path: Path) -> RecordingInfo:
        sig = _signature(path)
        cached = self._info.get(path)
        if cached is None or cached[0] != sig or cached[1].recording_now:
            self._info[path] = (sig, read_info(path))
        return self._info[path][1]

    def entry(self, path: str | Path, task: str | None = None) -> Entry:
        path = Path(path)
        info = self.info(path)
        meta_error = ""
        try:
            meta = read_meta(path)
        except MetaError as exc:
            meta, meta_error = DemoMeta(), str(exc)
        return Entry(path, info, meta, problems_of(path, info, meta_error, task))

    def scan(self, task: str | None = None) -> list[Entry]:
        """Every recording in the directory (``task``: flag recordings of another task)."""
        paths = recordings(self.directory)
        for gone in set(self._info) - set(paths):
            del self._info[gone]
        return [self.entry(p, task) for p in paths]

    def update(self, path: str | Path, **changes: Any) -> DemoMeta:
        """Change some metadata fields of one recording and store them; MetaError when a value is refused."""
        path = Path(path)
        known = {f.name for f in fields(DemoMeta)}
        unknown = sorted(set(changes) - known)
        if unknown:
            raise MetaError(f"unknown metadata field(s): {', '.join(unknown)}")
        try:
            meta = read_meta(path)
        except MetaError:  # an unreadable sidecar is replaced by what the teacher enters now
            meta = DemoMeta()
        for k, v in changes.items():
            setattr(meta, k, v)
        info = self.info(path)
        write_meta(path, meta, info.duration_s if info.messages else None)
        return meta


def next_demo_path(directory: str | Path, task: str, teacher: str, when: float | None = None) -> Path:
    """``<task>-<teacher>-YYYYmmdd-HHMMSS.mcap`` in ``directory``, suffixed rather than overwrite."""
    slug = "-".join(_slug(s) for s in (task or "demo", teacher) if _slug(s))
    stem = f"{slug}-{time.strftime('%Y%m%d-%H%M%S', time.localtime(when))}"
    path = Path(directory) / f"{stem}.mcap"
    n = 2
    while path.exists() or sidecar_path(path).exists():
        path = Path(directory) / f"{stem}-{n}.mcap"
        n += 1
    return path


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() or c in "_" else "_" for c in text.strip())[:40].strip("_")


def table(entries: Iterable[Entry], selected: Path | None = None) -> str:
    """The library as markdown: a table (name, duration, keys, label, split, outcome), then the
    trims and, for each recording that cannot be learned from, why."""
    rows = ["| demonstration | s | keys | label | split | outcome |", "|---|---|---|---|---|---|"]
    notes = []
    for e in entries:
        name = f"**{e.name}**" if selected is not None and e.path == selected else e.name
        dur = f"{e.info.duration_s:.1f}" if e.info.messages else "-"
        rows.append(f"| {name} | {dur} | {len(e.info.messages)} | {_cell(e.meta.label)} | {e.meta.split} | "
                    f"{e.meta.outcome} |")
        if e.meta.trim_start_s or e.meta.trim_end_s is not None:
            lo, hi = e.meta.window(e.info.duration_s)
            notes.append(f"- {e.name}: trimmed to {lo:.1f}-{hi:.1f} s")
        if e.problems:
            notes.append(f"- {e.name}: **not trainable**: {_cell('; '.join(e.problems))}")
    if len(rows) == 2:
        return "no recordings yet"
    return "\n".join(rows + ([""] + notes if notes else []))


def _cell(text: str) -> str:
    return text.replace("|", "/").replace("\n", " ") or "-"
