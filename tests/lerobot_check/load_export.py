"""Load an export with LeRobot's own ``LeRobotDataset`` and print what it sees as JSON (run by
tests/unit/test_lerobot_export.py with .cache/lerobot-site and this directory on the path).

Video frames are checked at the timestamps LeRobot would query (the episode's ``from_timestamp``
plus the frame's ``timestamp``) against the frames PyAV decodes: LeRobot's decoders need torchcodec
or torchvision's video reader, and the only wheels of either for torch 2.13.0 are CUDA builds."""

from __future__ import annotations

import json
import logging
import sys
import warnings

import av
import numpy as np


def main(root: str) -> None:
    caught: list[str] = []
    logging.basicConfig(level=logging.WARNING, handlers=[_Collect(caught)])
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        ds = LeRobotDataset("local/crossmodal", root=root, video_backend="pyav")
        episodes = ds.meta.episodes
        rows = list(ds.hf_dataset)
    caught += [f"{x.category.__name__}: {x.message}" for x in w
               if "lerobot" in str(x.filename) or "datasets" in str(x.filename)]
    first = ds[0] if not ds.meta.video_keys else rows[0]  # __getitem__ decodes video through torchcodec
    out = {
        "num_episodes": ds.num_episodes, "num_frames": ds.num_frames, "fps": ds.fps,
        "from": list(episodes["dataset_from_index"]), "to": list(episodes["dataset_to_index"]),
        "tasks": [ds.meta.tasks.iloc[int(r["task_index"])].name for r in rows[:1]],
        "shapes": {k: list(np.asarray(v).shape) for k, v in first.items() if k != "task"},
        "episode_of_row": [int(r["episode_index"]) for r in rows],
        "frame_of_row": [int(r["frame_index"]) for r in rows],
        "timestamps": [float(r["timestamp"]) for r in rows],
        "state_first": np.asarray(rows[0]["observation.state"]).tolist(),
        "camera_keys": ds.meta.camera_keys, "video_frames": {}, "warnings": caught,
    }
    decoded: dict[str, np.ndarray] = {}
    for key in ds.meta.video_keys:
        found = []
        for e in range(ds.num_episodes):
            ep = episodes[e]
            path = f"{root}/{ds.meta.get_video_file_path(e, key)}"
            if path not in decoded:
                decoded[path] = _frame_times(path)
            want = np.array([ep[f"videos/{key}/from_timestamp"] + float(r["timestamp"]) for r in rows
                             if int(r["episode_index"]) == e])
            have = decoded[path]
            near = np.clip(np.searchsorted(have, want), 1, len(have) - 1)
            gap = np.minimum(np.abs(have[near] - want), np.abs(have[near - 1] - want))
            found.append(int((gap <= ds.tolerance_s).sum()))
        out["video_frames"][key] = found
    print(json.dumps(out))


def _frame_times(path: str) -> np.ndarray:
    """Presentation times (s) of every decoded frame of a video, in order."""
    with av.open(path) as c:
        stream = c.streams.video[0]
        return np.sort([float(f.pts * stream.time_base) for f in c.decode(stream)])


class _Collect(logging.Handler):
    def __init__(self, into: list[str]) -> None:
        super().__init__(logging.WARNING)
        self.into = into

    def emit(self, record: logging.LogRecord) -> None:
        self.into.append(f"{record.levelname}: {record.getMessage()}")


if __name__ == "__main__":
    main(sys.argv[1])
