"""``xm export lerobot``: demonstrations of recordings -> a LeRobot dataset v3 directory.

Tables are written with pyarrow (Parquet), camera streams with PyAV (MP4, one file per camera
holding every episode one after the other, as LeRobot v3 stores them). Which streams go in is
decided by the first recording with demonstrations (or by the options); an episode that lacks one
of them (a recording without the robot's state or a camera, a stream that stops) is skipped and
the reason reported.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from interop import lerobot_format as fmt
from interop.recording_streams import Recording, camera_frame, camera_size, demos_with_starts, read_recording
from learning.dataset import DatasetError
from shared.demo import Demo
from shared.recording_files import segment_key

MAX_ROBOT_AGE_S = 0.5  # a joint state older than this at a frame: the robot's stream stopped
MAX_IMAGE_AGE_S = 1.0  # a camera frame older than this (nominal 5 Hz): the camera stopped
DATA_FILE_ROWS = 200_000  # rows per data file (~100 MB of LeRobot's limit at our row size)


@dataclass
class ExportOptions:
    fps: int = 50
    robot: str | None = "auto"  # state key, "auto" (the recording's one robot) or None (no joints)
    cameras: list[str] | None = None  # None: every camera of the first recording; []: no video
    vcodec: str = "libsvtav1"
    crf: int = 30
    robot_type: str | None = None


@dataclass
class ExportResult:
    episodes: int = 0
    frames: int = 0
    skipped: list[str] = field(default_factory=list)  # one line per skipped episode or recording
    report: list[str] = field(default_factory=list)  # what the demonstration reader masked or cut
    features: list[str] = field(default_factory=list)


@dataclass
class _Layout:
    """Streams of the dataset, fixed by the first recording with demonstrations."""

    object_names: list[str]
    robot_key: str | None
    joint_names: list[str] | None
    cameras: dict[str, tuple[int, int]]


def export(recordings: list[str | Path], out: str | Path, opts: ExportOptions | None = None) -> ExportResult:
    """Write the demonstrations of ``recordings`` as a LeRobot v3 dataset in ``out`` (replaced)."""
    opts = opts or ExportOptions()
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        if not (out / fmt.INFO_PATH).exists():
            raise FileExistsError(f"{out} exists and is not a LeRobot dataset; not overwriting it")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    res = ExportResult()
    layout: _Layout | None = None
    writer = _Writer(out, opts)
    dt = 1.0 / opts.fps
    for path in recording_list(recordings):
        try:
            rec = read_recording(path)
            demos = demos_with_starts(rec, dt, res.report)
        except DatasetError as exc:
            res.skipped.append(f"{path}: skipped: {exc}")
            continue
        if rec.malformed:
            res.report.append(f"{path}: {rec.malformed} messages that do not decode as their key's type left out")
        if layout is None:
            layout = _layout(rec, demos[0][0], opts)
        for demo, t0 in demos:
            name = f"{path}: demonstration {demo.meta.get('demo')}"
            try:
                ep = _episode(rec, demo, t0, layout, dt)
            except DatasetError as exc:
                res.skipped.append(f"{name}: skipped: {exc}")
                continue
            writer.add(ep)
    if layout is None or not writer.episodes:
        shutil.rmtree(out)
        raise DatasetError("nothing exported: " + ("; ".join(res.skipped) or "no recordings given"))
    feats = fmt.features(layout.object_names, layout.joint_names, layout.cameras, opts.fps, opts.vcodec)
    writer.close(feats, opts.robot_type)
    res.episodes, res.frames, res.features = len(writer.episodes), writer.frames, list(feats)
    return res


def recording_list(paths: list[str | Path]) -> list[Path]:
    """Each recording once, by its first segment: a directory gives every recording in it (by name),
    a later segment whose first one is also given is part of that one."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out += sorted(f for f in p.glob("*.mcap") if f.is_file() and segment_key(f)[1] == 0)
        else:
            out.append(p)
    firsts = {(f.parent, segment_key(f)[0]) for f in out if segment_key(f)[1] == 0}
    return [f for f in out if segment_key(f)[1] == 0 or (f.parent, segment_key(f)[0]) not in firsts]


def _layout(rec: Recording, demo: Demo, opts: ExportOptions) -> _Layout:
    robot_key = None
    if opts.robot == "auto":
        robot_key = sorted(rec.robots)[0] if rec.robots else None
    elif opts.robot:
        robot_key = opts.robot
    joint_names = list(rec.robots[robot_key].values[0][0]) if robot_key in rec.robots else None
    if robot_key is not None and joint_names is None:
        raise DatasetError(f"{rec.source}: no messages on the robot state key {robot_key}")
    names = sorted(rec.images) if opts.cameras is None else list(opts.cameras)
    cameras = {}
    for cam in names:
        size = camera_size(rec, cam) if cam in rec.images else None
        if size is None:
            raise DatasetError(f"{rec.source}: no decodable frames of camera {cam!r} (cameras: "
                               f"{', '.join(sorted(rec.images)) or 'none'})")
        cameras[cam] = (size[0] // 2 * 2, size[1] // 2 * 2)  # yuv420p needs even sizes
    return _Layout(list(demo.object_names), robot_key, joint_names, cameras)


def _sampled(stream, times: np.ndarray, max_age: float, missing: str, first: str, gap: str) -> np.ndarray:
    """Indices of ``stream``'s samples at ``times``; DatasetError when the stream is missing, starts
    late or has a gap over ``max_age`` seconds (the messages name what is missing)."""
    if stream is None:
        raise DatasetError(f"no {missing}")
    idx, age = stream.at(times)
    if not np.isfinite(age):
        raise DatasetError(f"no {first} at its start")
    if age > max_age:
        raise DatasetError(f"a gap of {age:.2f} s in {gap} (at most {max_age} s allowed)")
    return idx


def _episode(rec: Recording, demo: Demo, t0: float, layout: _Layout, dt: float) -> fmt.Episode:
    if list(demo.object_names) != layout.object_names:
        raise DatasetError(f"object keypoints {demo.object_names} differ from the dataset's {layout.object_names}")
    times = t0 + np.arange(demo.steps) * dt
    ep = fmt.Episode(demo=demo, task=str(demo.meta.get("task") or "demonstration"))
    if layout.robot_key is not None:
        stream = rec.robots.get(layout.robot_key)
        idx = _sampled(stream, times, MAX_ROBOT_AGE_S, f"robot joint states ({layout.robot_key} missing from the "
                       "recording)", f"robot joint state on {layout.robot_key}",
                       f"the robot joint states on {layout.robot_key}")
        n = len(layout.joint_names)
        if any(stream.values[i][0] != layout.joint_names for i in set(idx.tolist())):
            raise DatasetError(f"joint names on {layout.robot_key} differ from {layout.joint_names}")
        if any(len(stream.values[i][1]) != n for i in set(idx.tolist())):
            raise DatasetError(f"joint states on {layout.robot_key} without one position per joint")
        ep.joints = np.stack([stream.values[i][1] for i in idx])
        if not np.isfinite(ep.joints).all():
            raise DatasetError(f"non-finite joint positions on {layout.robot_key}")
    for cam, size in layout.cameras.items():
        stream = rec.images.get(cam)
        idx = _sampled(stream, times, MAX_IMAGE_AGE_S, f"frames of camera {cam!r} (xm/camhub/{cam}/image missing "
                       "from the recording)", f"frame of camera {cam!r}", f"the frames of camera {cam!r}")
        infos = rec.infos.get(cam, {})
        decoded: dict[int, np.ndarray] = {}
        frames = []
        for i in idx.tolist():
            if i not in decoded:
                try:
                    decoded[i] = camera_frame(stream.values[i], size, infos.get(stream.stamps[i]))
                except ValueError as exc:
                    raise DatasetError(f"camera {cam!r}: frame at {stream.stamps[i] - t0:.2f} s: {exc}") from None
            frames.append(decoded[i])
        ep.images[cam] = frames
    return ep


class _Writer:
    """Appends episodes: data rows to Parquet files, frames to one MP4 per camera."""

    def __init__(self, root: Path, opts: ExportOptions) -> None:
        self.root, self.opts = root, opts
        self.episodes: list[dict] = []
        self.frames = 0
        self.tasks: dict[str, int] = {}
        self.data_file = 0
        self.rows_in_file = 0
        self.pending: list[dict[str, np.ndarray]] = []
        self.columns: dict[str, list[np.ndarray]] = {}  # every row, for stats
        self.videos: dict[str, _Video] = {}
        self.image_samples: dict[str, list[np.ndarray]] = {}

    def add(self, ep: fmt.Episode) -> None:
        task_index = self.tasks.setdefault(ep.task, len(self.tasks))
        index = len(self.episodes)
        cols = fmt.frame_columns(ep, index, self.frames, task_index)
        n = ep.demo.steps
        if self.rows_in_file and self.rows_in_file + n > DATA_FILE_ROWS:
            self._flush_data()
            self.data_file += 1
            self.rows_in_file = 0
        row = {"episode_index": index, "tasks": [ep.task], "length": n,
               "data/chunk_index": self.data_file // fmt.CHUNK_SIZE, "data/file_index": self.data_file % fmt.CHUNK_SIZE,
               "dataset_from_index": self.frames, "dataset_to_index": self.frames + n}
        for cam, frames in ep.images.items():
            video = self.videos.get(cam)
            if video is None:
                video = self.videos[cam] = _Video(self.root / fmt.VIDEO_PATH.format(
                    video_key=fmt.IMAGE_PREFIX + cam, chunk_index=0, file_index=0), frames[0].shape, self.opts)
            start = video.frames
            video.write(frames)
            key = f"videos/{fmt.IMAGE_PREFIX}{cam}"
            row |= {f"{key}/chunk_index": 0, f"{key}/file_index": 0,
                    f"{key}/from_timestamp": start / self.opts.fps, f"{key}/to_timestamp": video.frames / self.opts.fps}
            self.image_samples.setdefault(cam, []).extend(frames[:: max(1, n // 10)])
        row |= {"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0,
                "xm_meta": json.dumps(ep.demo.meta, default=str)}
        self.episodes.append(row)
        self.pending.append(cols)
        for k, v in cols.items():
            self.columns.setdefault(k, []).append(v)
        self.rows_in_file += n
        self.frames += n

    def _flush_data(self) -> None:
        if not self.pending:
            return
        cols = {k: np.concatenate([c[k] for c in self.pending]) for k in self.pending[0]}
        path = self.root / fmt.DATA_PATH.format(chunk_index=self.data_file // fmt.CHUNK_SIZE,
                                                file_index=self.data_file % fmt.CHUNK_SIZE)
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table({k: _arrow(v) for k, v in cols.items()}), path, compression="snappy")
        self.pending = []

    def close(self, feats: dict, robot_type: str | None) -> None:
        self._flush_data()
        for v in self.videos.values():
            v.close()
        meta = self.root / "meta"
        ep_path = self.root / fmt.EPISODES_PATH
        ep_path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_pylist(self.episodes), ep_path, compression="snappy")
        _write_tasks(self.root / fmt.TASKS_PATH, self.tasks)
        stats = {k: fmt.feature_stats(np.concatenate(v)) for k, v in self.columns.items()}
        stats |= {fmt.IMAGE_PREFIX + cam: fmt.image_stats(s) for cam, s in self.image_samples.items()}
        (meta / "stats.json").write_text(json.dumps(stats, indent=2))
        info = fmt.info(self.opts.fps, feats, len(self.episodes), self.frames, len(self.tasks), robot_type,
                        bool(self.videos))
        (meta / "info.json").write_text(json.dumps(info, indent=2))


def _arrow(x: np.ndarray) -> pa.Array:
    """A column: scalars as they are, vectors as fixed-size lists (LeRobot's Sequence(length=D))."""
    if x.ndim == 1:
        return pa.array(x)
    return pa.FixedSizeListArray.from_arrays(pa.array(x.reshape(-1)), x.shape[1])


def _write_tasks(path: Path, tasks: dict[str, int]) -> None:
    """meta/tasks.parquet: ``task_index`` with the task text as the pandas index (what LeRobot's
    ``pd.read_parquet`` expects), written with pyarrow and the pandas schema metadata."""
    names = sorted(tasks, key=tasks.get)
    table = pa.table({"task_index": pa.array([tasks[n] for n in names], pa.int64()), "task": pa.array(names)})
    pandas_meta = {
        "index_columns": ["task"],
        "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object",
                            "metadata": {"encoding": "UTF-8"}}],
        "columns": [{"name": "task_index", "field_name": "task_index", "pandas_type": "int64",
                     "numpy_type": "int64", "metadata": None},
                    {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object",
                     "metadata": None}],
        "creator": {"library": "pyarrow", "version": pa.__version__}, "pandas_version": "2.2.0"}
    table = table.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode()})
    pq.write_table(table, path)


class _Video:
    """One camera's MP4: frame n at pts n (time base 1 / fps), key frame every 2 frames as LeRobot
    encodes, so a frame is found exactly by its timestamp."""

    def __init__(self, path: Path, shape: tuple[int, ...], opts: ExportOptions) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its configuration and warnings otherwise
        self.container = av.open(str(path), mode="w")
        self.stream = self.container.add_stream(opts.vcodec, rate=opts.fps)
        self.stream.width, self.stream.height = shape[1], shape[0]
        self.stream.pix_fmt = "yuv420p"
        self.stream.time_base = Fraction(1, opts.fps)
        options = {"g": "2", "crf": str(opts.crf)}
        if opts.vcodec == "libsvtav1":
            options["preset"] = "12"  # the fastest preset: exports run on busy CPUs
        self.stream.options = options
        self.frames = 0

    def write(self, frames: list[np.ndarray]) -> None:
        for img in frames:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24")
            frame.pts = self.frames
            for packet in self.stream.encode(frame):
                self.container.mux(packet)
            self.frames += 1

    def close(self) -> None:
        for packet in self.stream.encode(None):
            self.container.mux(packet)
        self.container.close()
