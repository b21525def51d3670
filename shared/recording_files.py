"""Which files make up a recording: the recorder writes MCAP segments ``NAME.mcap``,
``NAME.seg0001.mcap``, ``NAME.seg0002.mcap``, ... (services/recorder/segments.py); readers (replay,
training) take a recording as one segment's path, a directory of recordings, or a list of files,
and read the segments in order."""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

_SEGMENT = re.compile(r"^(?P<base>.*?)(?:\.seg(?P<index>\d+))?\.mcap$")


def segment_path(first: str | Path, index: int) -> Path:
    """The path of segment ``index`` of the recording whose first segment is ``first``."""
    first = Path(first)
    if index == 0:
        return first
    stem = first.name[:-len(".mcap")] if first.name.endswith(".mcap") else first.name
    return first.with_name(f"{stem}.seg{index:04d}.mcap")


def segment_key(path: Path) -> tuple[str, int]:
    """(recording name, segment index) of a segment file."""
    m = _SEGMENT.match(path.name)
    if m is None:
        return path.name, 0
    return m["base"], int(m["index"] or 0)


def recording_segments(source: str | Path | Iterable[str | Path]) -> list[Path]:
    """The segment files of a recording in order: a first segment's path gives it and its existing
    ``.segNNNN`` siblings, a directory every ``*.mcap`` in it (recordings by name, segments by index),
    a list the files it names (each expanded the same way). Paths that do not exist are kept, so the
    reader reports them."""
    if isinstance(source, (str, Path)):
        path = Path(source)
        if path.is_dir():
            files = [p for p in path.glob("*.mcap") if p.is_file()]
            return sorted(files, key=lambda p: (segment_key(p), p.name))
        base, index = segment_key(path)
        if index or not path.name.endswith(".mcap"):
            return [path]
        siblings = [p for p in path.parent.glob(f"{glob_escape(base)}.seg*.mcap") if segment_key(p)[0] == base]
        return [path] + sorted(siblings, key=segment_key)
    out: list[Path] = []
    for item in source:
        out += [p for p in recording_segments(item) if p not in out]
    return out


def glob_escape(text: str) -> str:
    return re.sub(r"([*?\[])", r"[\1]", text)
