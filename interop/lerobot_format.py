"""LeRobot dataset v3 layout of our demonstrations (pure: arrays and dictionaries, no I/O).

One demonstration is one episode; one frame is one time step of the demonstration (``Demo.dt``,
so the dataset's fps is 1 / dt). Columns of a frame:

- ``observation.state``: hand keypoints (left then right, 21 each, x y z) and the object
  keypoints (x y z each), metres, float32; ``observation.state_mask``: 1 where observed.
- ``action``: the same keypoints one step later (the last frame repeats its own state): the
  target a keypoint policy is trained to reach.
- ``observation.environment_state``: the object keypoints alone (LeRobot's name for the state of
  the world around the robot, which state-only policies such as its Diffusion Policy take).
- ``observation.tactile`` / ``observation.tactile_mask``: 2 hands x 6 regions, kPa.
- ``observation.robot_joints``: the robot's measured joint positions (when exported).
- ``observation.phase``: index into the phase names of the feature's ``names``.
- ``observation.images.<camera>``: a video feature per camera.

LeRobot's own columns: ``timestamp`` (seconds from the episode start), ``frame_index``,
``episode_index``, ``index`` (over the dataset) and ``task_index``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from shared.demo import HAND_NAMES, KEYPOINTS_PER_HAND, TACTILE_REGIONS, Demo

CODEBASE_VERSION = "v3.0"
CHUNK_SIZE = 1000  # files per chunk directory, LeRobot's default
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
TASKS_PATH = "meta/tasks.parquet"
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
PHASES = ("", "approach", "grasp", "place", "press", "lift", "done")
IMAGE_PREFIX = "observation.images."
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)


class FormatError(ValueError):
    """A dataset directory or an episode that does not fit the layout; the message says which part."""


def keypoint_names(object_names: list[str]) -> list[str]:
    """One name per state dimension: ``left/4/x``, ..., ``cup/rim/z``."""
    points = [f"{h}/{k}" for h in HAND_NAMES for k in range(KEYPOINTS_PER_HAND)] + list(object_names)
    return [f"{p}/{axis}" for p in points for axis in "xyz"]


def point_names(object_names: list[str]) -> list[str]:
    return [f"{h}/{k}" for h in HAND_NAMES for k in range(KEYPOINTS_PER_HAND)] + list(object_names)


def object_names_of(state_names: list[str]) -> list[str]:
    """The object keypoint names back from ``observation.state``'s names."""
    points = [n.rsplit("/", 1)[0] for n in state_names[::3]]
    hands = len(HAND_NAMES) * KEYPOINTS_PER_HAND
    if len(state_names) % 3 or len(points) < hands:
        raise FormatError(f"observation.state has {len(state_names)} names; expected 3 per point and "
                          f"{hands} hand points first")
    return points[hands:]


def tactile_names() -> list[str]:
    return [f"{h}/{r}" for h in HAND_NAMES for r in TACTILE_REGIONS]


@dataclass
class Episode:
    """One demonstration ready to be written: its frame columns and, per camera, its frames."""

    demo: Demo
    task: str
    joints: np.ndarray | None = None  # (T, J) float32
    images: dict[str, list[np.ndarray]] = field(default_factory=dict)  # camera -> T frames (H, W, 3) RGB


def features(object_names: list[str], joint_names: list[str] | None, cameras: dict[str, tuple[int, int]],
             fps: int, vcodec: str) -> dict:
    """``info.json`` ``features`` for these streams; ``cameras``: name -> (height, width)."""
    p = len(point_names(object_names))
    names = keypoint_names(object_names)
    out: dict = {
        "observation.state": {"dtype": "float32", "shape": [3 * p], "names": names},
        "observation.state_mask": {"dtype": "float32", "shape": [p], "names": point_names(object_names)},
        "action": {"dtype": "float32", "shape": [3 * p], "names": names},
        "observation.environment_state": {"dtype": "float32", "shape": [3 * len(object_names)],
                                          "names": names[3 * (p - len(object_names)):]},
        "observation.tactile": {"dtype": "float32", "shape": [len(tactile_names())], "names": tactile_names()},
        "observation.tactile_mask": {"dtype": "float32", "shape": [len(tactile_names())], "names": tactile_names()},
        "observation.phase": {"dtype": "int64", "shape": [1], "names": list(PHASES)},
    }
    if joint_names is not None:
        out["observation.robot_joints"] = {"dtype": "float32", "shape": [len(joint_names)], "names": joint_names}
    for cam, (h, w) in cameras.items():
        out[IMAGE_PREFIX + cam] = {
            "dtype": "video", "shape": [h, w, 3], "names": ["height", "width", "channels"],
            "info": {"video.height": h, "video.width": w, "video.codec": _codec_name(vcodec),
                     "video.pix_fmt": "yuv420p", "video.is_depth_map": False, "video.fps": fps,
                     "video.channels": 3, "has_audio": False}}
    for name, dtype in (("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"),
                        ("index", "int64"), ("task_index", "int64")):
        out[name] = {"dtype": dtype, "shape": [1], "names": None}
    return out


def _codec_name(vcodec: str) -> str:
    return {"libsvtav1": "av1", "libaom-av1": "av1", "libx264": "h264", "libx265": "hevc"}.get(vcodec, vcodec)


def frame_columns(ep: Episode, episode_index: int, first_index: int, task_index: int) -> dict[str, np.ndarray]:
    """The data columns of one episode (arrays with one row per frame)."""
    d = ep.demo
    t = d.steps
    state = np.concatenate([d.hands.reshape(t, -1), d.objects.reshape(t, -1)], axis=1).astype(np.float32)
    mask = np.concatenate([d.hand_mask.reshape(t, -1), d.object_mask], axis=1).astype(np.float32)
    action = np.concatenate([state[1:], state[-1:]], axis=0)
    phases = [PHASES.index(p) if p in PHASES else 0 for p in (d.phase or [""] * t)]
    cols = {
        "observation.state": state,
        "observation.state_mask": mask,
        "action": action,
        "observation.environment_state": d.objects.reshape(t, -1).astype(np.float32),
        "observation.tactile": d.tactile.reshape(t, -1).astype(np.float32),
        "observation.tactile_mask": d.tactile_mask.reshape(t, -1).astype(np.float32),
        "observation.phase": np.asarray(phases, np.int64),
        "timestamp": (np.arange(t) * d.dt).astype(np.float32),
        "frame_index": np.arange(t, dtype=np.int64),
        "episode_index": np.full(t, episode_index, np.int64),
        "index": np.arange(first_index, first_index + t, dtype=np.int64),
        "task_index": np.full(t, task_index, np.int64),
    }
    if ep.joints is not None:
        cols["observation.robot_joints"] = ep.joints.astype(np.float32)
    return cols


def feature_stats(x: np.ndarray) -> dict[str, list]:
    """min, max, mean, std, count and LeRobot's quantiles over axis 0 of (N, D) values."""
    x = np.asarray(x, np.float64).reshape(len(x), -1)
    out = {"min": x.min(0), "max": x.max(0), "mean": x.mean(0), "std": x.std(0)}
    for q in QUANTILES:
        out[f"q{int(round(q * 100)):02d}"] = np.quantile(x, q, axis=0)
    res = {k: v.tolist() for k, v in out.items()}
    res["count"] = [int(len(x))]
    return res


def image_stats(frames: list[np.ndarray]) -> dict[str, list]:
    """Per-channel stats of RGB frames scaled to [0, 1], shaped (3, 1, 1) as LeRobot keeps them."""
    px = np.concatenate([f.reshape(-1, 3) for f in frames[:: max(1, len(frames) // 100)]]).astype(np.float64) / 255.0
    s = feature_stats(px)
    return {k: (v if k == "count" else [[[c]] for c in v]) for k, v in s.items()} | {"count": [len(frames)]}


def episode_to_demo(cols: dict[str, np.ndarray], object_names: list[str], fps: float, meta: dict) -> Demo:
    """One episode's columns back into a Demo (the inverse of ``frame_columns``)."""
    state = np.asarray(cols["observation.state"], np.float32)
    mask = np.asarray(cols["observation.state_mask"])
    t = len(state)
    hands_n = len(HAND_NAMES) * KEYPOINTS_PER_HAND
    k = len(object_names)
    if state.shape != (t, 3 * (hands_n + k)) or mask.shape != (t, hands_n + k):
        raise FormatError(f"episode {meta.get('episode_index')}: observation.state {state.shape} / mask {mask.shape}"
                          f" do not fit {hands_n} hand and {k} object points")
    pts = state.reshape(t, hands_n + k, 3)
    phase_idx = np.asarray(cols.get("observation.phase", np.zeros(t, np.int64))).reshape(t)
    shape_t = (t, len(HAND_NAMES), len(TACTILE_REGIONS))
    return Demo(dt=1.0 / fps,
                hands=pts[:, :hands_n].reshape(t, len(HAND_NAMES), KEYPOINTS_PER_HAND, 3).copy(),
                hand_mask=mask[:, :hands_n].reshape(t, len(HAND_NAMES), KEYPOINTS_PER_HAND).astype(np.uint8),
                object_names=list(object_names), objects=pts[:, hands_n:].copy(),
                object_mask=mask[:, hands_n:].astype(np.uint8),
                tactile=np.asarray(cols["observation.tactile"], np.float32).reshape(shape_t),
                tactile_mask=np.asarray(cols["observation.tactile_mask"]).reshape(shape_t).astype(np.uint8),
                phase=[PHASES[int(i)] if 0 <= int(i) < len(PHASES) else "" for i in phase_idx], meta=dict(meta))


def info(fps: int, feats: dict, episodes: int, frames: int, tasks: int, robot_type: str | None,
         has_video: bool) -> dict:
    """``meta/info.json``."""
    return {"codebase_version": CODEBASE_VERSION, "robot_type": robot_type, "total_episodes": episodes,
            "total_frames": frames, "total_tasks": tasks, "chunks_size": CHUNK_SIZE, "data_files_size_in_mb": 100,
            "video_files_size_in_mb": 200, "fps": fps, "splits": {"train": f"0:{episodes}"},
            "data_path": DATA_PATH, "video_path": VIDEO_PATH if has_video else None, "features": feats}


def check_info(info_: dict) -> None:
    """Refuse what our reader (and LeRobot's) cannot read, saying which field."""
    for key in ("codebase_version", "fps", "features", "data_path", "total_episodes"):
        if key not in info_:
            raise FormatError(f"meta/info.json has no {key!r}")
    if not str(info_["codebase_version"]).startswith("v3."):
        raise FormatError(f"codebase_version {info_['codebase_version']!r}: only LeRobot v3 datasets are read")
    for key in ("observation.state", "observation.state_mask", "observation.tactile", "observation.tactile_mask"):
        if key not in info_["features"]:
            raise FormatError(f"feature {key!r} missing: not a crossmodal export (state, masks and tactile needed)")
