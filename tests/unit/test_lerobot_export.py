"""LeRobot dataset v3 export and import (interop/): layout, round trip, skipped episodes, and the
export read by LeRobot's own dataset class where it is installed beside the venv."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import av
import numpy as np
import pyarrow.parquet as pq
import pytest

from interop import lerobot_format as fmt
from interop.cli import export_main, import_main
from interop.lerobot_export import ExportOptions, export, recording_list
from interop.lerobot_import import import_dataset
from learning.dataset import DatasetError, demos_from_mcap
from shared.demo import Demo
from tests.unit.lerobot_recordings import write_session

ROOT = Path(__file__).resolve().parents[2]
LEROBOT_SITE = ROOT / ".cache" / "lerobot-site"
FPS = 50


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> tuple[list[Path], Path]:
    d = tmp_path_factory.mktemp("lerobot")
    recs = [write_session(d / "a.mcap", demos=3, seed=0), write_session(d / "b.mcap", demos=2, seed=1)]
    out = d / "dataset"
    res = export(recs, out, ExportOptions(fps=FPS, vcodec="libsvtav1"))
    assert res.episodes == 5 and not res.skipped
    return recs, out


def test_layout_is_lerobot_v3(session):
    _, out = session
    info = json.loads((out / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == FPS
    assert info["total_episodes"] == 5 and info["total_tasks"] == 1
    feats = info["features"]
    assert feats["observation.state"]["shape"] == [3 * (42 + 3)]
    assert feats["observation.robot_joints"]["names"] == ["x", "y", "z", "yaw"]
    assert feats["observation.images.cam0"]["dtype"] == "video"
    assert feats["observation.images.cam0"]["shape"] == [48, 64, 3]
    episodes = pq.read_table(out / fmt.EPISODES_PATH).to_pylist()
    data = pq.read_table(out / "data/chunk-000/file-000.parquet")
    assert data.num_rows == info["total_frames"] == sum(e["length"] for e in episodes)
    # episodes tile the rows in order, each one's timestamps restart at 0 and step by 1 / fps
    ends = [e["dataset_from_index"] for e in episodes[1:]] + [info["total_frames"]]
    assert [e["dataset_to_index"] for e in episodes] == ends and episodes[0]["dataset_from_index"] == 0
    ep_col = data.column("episode_index").to_numpy()
    ts = data.column("timestamp").to_numpy()
    for e in episodes:
        rows = slice(e["dataset_from_index"], e["dataset_to_index"])
        assert (ep_col[rows] == e["episode_index"]).all()
        np.testing.assert_allclose(ts[rows], np.arange(e["length"]) / FPS, atol=1e-6)
    tasks = pq.read_table(out / fmt.TASKS_PATH)
    assert tasks.column("task").to_pylist() == ["assembly"]
    assert json.loads(tasks.schema.metadata[b"pandas"])["index_columns"] == ["task"]
    stats = json.loads((out / "meta/stats.json").read_text())
    assert len(stats["observation.state"]["mean"]) == 135 and stats["observation.state"]["count"] == [data.num_rows]
    assert np.asarray(stats["observation.images.cam0"]["mean"]).shape == (3, 1, 1)


def test_video_holds_one_frame_per_row_at_its_timestamp(session):
    _, out = session
    episodes = pq.read_table(out / fmt.EPISODES_PATH).to_pylist()
    with av.open(str(out / "videos/observation.images.cam1/chunk-000/file-000.mp4")) as c:
        stream = c.streams.video[0]
        frames = [(float(f.pts * stream.time_base), f.to_ndarray(format="rgb24")) for f in c.decode(stream)]
    assert len(frames) == sum(e["length"] for e in episodes)
    times = np.array([t for t, _ in frames])
    np.testing.assert_allclose(times, np.arange(len(frames)) / FPS, atol=1e-9)
    for e in episodes:
        key = "videos/observation.images.cam1"
        assert e[f"{key}/to_timestamp"] - e[f"{key}/from_timestamp"] == pytest.approx(e["length"] / FPS)
    # the windows around the hands sit where their camera info puts them, black around them
    windows = [img for _, img in frames if img[0, 0].max() < 20 and img[16, 24].min() > 50]
    assert windows and all(img.shape == (48, 64, 3) for _, img in frames)


def test_round_trip_keeps_every_keypoint(session):
    recs, out = session
    back = import_dataset(out)
    want = [d for r in recs for d in demos_from_mcap(r, dt=1.0 / FPS)]
    assert len(back) == len(want) == 5
    for a, b in zip(want, back, strict=True):
        assert b.dt == pytest.approx(a.dt) and b.steps == a.steps
        assert b.object_names == a.object_names
        np.testing.assert_array_equal(b.hands, a.hands)  # float32 in, float32 out: bit for bit
        np.testing.assert_array_equal(b.objects, a.objects)
        np.testing.assert_array_equal(b.hand_mask, a.hand_mask)
        np.testing.assert_array_equal(b.object_mask, a.object_mask)
        np.testing.assert_array_equal(b.tactile, a.tactile)
        np.testing.assert_array_equal(b.tactile_mask, a.tactile_mask)
        assert b.phase == a.phase
        assert b.meta["demo"] == a.meta["demo"] and b.meta["grasp_hand"] == a.meta["grasp_hand"]


def test_cli_round_trip(session, tmp_path, capsys):
    recs, _ = session
    out = tmp_path / "ds"
    assert export_main(["lerobot", str(recs[1]), "-o", str(out), "--cameras", "none", "--robot", "none"]) == 0
    assert "2 episodes" in capsys.readouterr().out
    info = json.loads((out / "meta/info.json").read_text())
    assert "observation.robot_joints" not in info["features"] and info["video_path"] is None
    assert import_main(["lerobot", str(out), "-o", str(tmp_path / "demos")]) == 0
    files = sorted((tmp_path / "demos").glob("*.npz"))
    lengths = [e["length"] for e in pq.read_table(out / fmt.EPISODES_PATH).to_pylist()]
    assert [Demo.load(f).steps for f in files] == lengths


def test_missing_keys_skip_the_episode_with_the_reason(tmp_path):
    good = write_session(tmp_path / "good.mcap", demos=2)
    cut = write_session(tmp_path / "cut.mcap", demos=2, robot_stops=2.0)  # the robot's state stops in demo 0
    blind = write_session(tmp_path / "blind.mcap", demos=1, cameras=("cam0",))
    other = write_session(tmp_path / "other.mcap", demos=1, joint_names=["a", "b"])
    empty = write_session(tmp_path / "empty.mcap", demos=0)
    res = export([good, cut, blind, other, empty], tmp_path / "ds", ExportOptions(vcodec="mpeg4"))
    text = "\n".join(res.skipped)
    assert res.episodes == 2, text  # good's two
    assert (f"{cut}: demonstration 0: skipped: a gap of 0.51 s in the robot joint states on "
            "xm/robot/workcell/state") in text
    assert f"{cut}: demonstration 1: skipped: a gap of" in text
    assert f"{blind}: demonstration 0: skipped: no frames of camera 'cam1'" in text
    assert f"{other}: demonstration 0: skipped: joint names" in text
    assert f"{empty}: skipped:" in text and "xm/recon/main/scene" in text


def test_a_directory_is_its_recordings_each_once(session, tmp_path):
    recs, _ = session
    seg = recs[0].with_name("a.seg0001.mcap")
    assert recording_list([recs[0].parent]) == sorted(recs)  # a.mcap, b.mcap: not one merged recording
    assert recording_list([recs[0], seg, recs[1]]) == [recs[0], recs[1]]


def test_nothing_to_export_is_an_error(tmp_path):
    empty = write_session(tmp_path / "empty.mcap", demos=0)
    with pytest.raises(DatasetError, match="nothing exported"):
        export([empty, tmp_path / "absent.mcap"], tmp_path / "ds")
    assert not (tmp_path / "ds").exists()
    assert export_main(["lerobot", str(empty), "-o", str(tmp_path / "ds")]) == 2


def test_import_refuses_what_it_cannot_read(tmp_path):
    with pytest.raises(fmt.FormatError, match="not a LeRobot v3 dataset"):
        import_dataset(tmp_path)
    (tmp_path / "meta").mkdir()
    (tmp_path / "meta/info.json").write_text(json.dumps({"codebase_version": "v2.1", "fps": 30, "features": {},
                                                         "data_path": "x", "total_episodes": 0}))
    with pytest.raises(fmt.FormatError, match="only LeRobot v3"):
        import_dataset(tmp_path)
    assert import_main(["lerobot", str(tmp_path)]) == 2


needs_lerobot = pytest.mark.skipif(
    not LEROBOT_SITE.exists(), reason="LeRobot is not installed beside the venv: .venv/bin/pip install --target "
    ".cache/lerobot-site --no-deps -r tests/lerobot_check/requirements.txt (docs/lerobot.md)")


def run_lerobot(script: str, *args: str) -> dict:
    """A script of tests/lerobot_check in a process that sees LeRobot; its last stdout line as JSON."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT / "tests/lerobot_check"), str(LEROBOT_SITE),
                                                       str(ROOT / "interop/lerobot_shim")]),
               HF_HUB_OFFLINE="1", HF_DATASETS_CACHE=str(Path(args[0]).parent / "hf-cache"))
    proc = subprocess.run([sys.executable, str(ROOT / "tests/lerobot_check" / script), *args],
                          capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@needs_lerobot
def test_lerobot_dataset_class_reads_the_export(session):
    _, out = session
    seen = run_lerobot("load_export.py", str(out))
    info = json.loads((out / "meta/info.json").read_text())
    episodes = pq.read_table(out / fmt.EPISODES_PATH).to_pylist()
    assert seen["warnings"] == []
    assert seen["fps"] == FPS and seen["num_episodes"] == 5 and seen["num_frames"] == info["total_frames"]
    assert seen["from"] == [e["dataset_from_index"] for e in episodes]
    assert seen["to"] == [e["dataset_to_index"] for e in episodes]
    assert seen["shapes"]["observation.state"] == [135] and seen["shapes"]["action"] == [135]
    assert seen["shapes"]["observation.environment_state"] == [9]
    assert seen["shapes"]["observation.robot_joints"] == [4] and seen["tasks"] == ["assembly"]
    lengths = [e["length"] for e in episodes]
    assert seen["episode_of_row"] == [i for i, n in enumerate(lengths) for _ in range(n)]
    assert seen["frame_of_row"] == [k for n in lengths for k in range(n)]
    assert seen["camera_keys"] == ["observation.images.cam0", "observation.images.cam1"]
    assert seen["video_frames"] == {k: lengths for k in seen["camera_keys"]}
    first = import_dataset(out)[0]
    np.testing.assert_array_equal(np.asarray(seen["state_first"], np.float32)[:63], first.hands[0, 0].ravel())


@needs_lerobot
def test_lerobot_diffusion_policy_trains_on_the_export(session, tmp_path):
    recs, _ = session
    out = tmp_path / "dataset"  # no cameras: LeRobot decodes video only through CUDA-built packages here
    export(recs, out, ExportOptions(fps=FPS, cameras=[]))
    seen = run_lerobot("train_policy.py", str(out), "5")
    losses = seen["losses"]
    assert len(losses) == 5 and all(np.isfinite(losses))
    assert losses[-1] < losses[0]  # the optimizer moves the policy on these batches
    assert seen["state_window"] == [2, 135] and seen["action_window"] == [8, 135]
    assert seen["action_is_pad"][0] and not any(seen["action_is_pad"][1:])  # frame 0 has no past action
