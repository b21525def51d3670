"""`xm recon REC.mcap -o OUT.mcap` on a small synthetic recording (services/recon/cli.py, offline.py)."""

from __future__ import annotations

import sys
import types

import cv2
import numpy as np
import pytest

from services.recon import cli
from services.recon.cli import MESH_KEY, SCENE_KEY, Frames, main
from services.recon.detector import CameraModel
from services.recon.hand_model import CHAINS, N_PARAMS
from services.recon.objects import task_keypoint_names
from services.recon.offline import OfflineConfig, fill_gaps, segments
from services.recon.triangulation import project
from services.recorder.writer import McapRecorder, read_messages
from services.world.model import camera_specs
from services.world.sim import WorldSim
from shared import msgs
from shared.demo import KEYPOINTS_PER_HAND
from shared.geometry import projection


def _recording(path, frames: int = 16) -> np.ndarray:
    """A teacher demonstration at 5 Hz: CameraInfo, truth and cam0's image per frame set."""
    sim = WorldSim("assembly", seed=7311)
    rec = McapRecorder(path)
    truth = []
    for f in range(frames):
        sim.step(100)
        t = 100.0 + 0.2 * f
        names, objects = sim.object_keypoints()
        hands = sim.hand_keypoints()
        hv, ov = sim.visibility()
        truth.append(hands.reshape(-1, 3))
        header = msgs.header(t, "world")
        rec.write("xm/world/sim/truth", "xm_msgs/msg/GroundTruth", msgs.serialize(msgs.make(
            "xm_msgs/msg/GroundTruth", header=header, hand_names=["left", "right"],
            hand_keypoints=hands.astype(np.float32).ravel(), hand_visible=np.asarray(hv, np.uint8).ravel(),
            object_names=names, object_keypoints=objects.astype(np.float32).ravel(),
            object_visible=np.asarray(ov, np.uint8), body_names=[], body_poses=np.zeros(0, np.float32),
            contact_forces=np.zeros(12, np.float32))), int(t * 1e9))
        for spec in camera_specs(256, 192):
            rec.write(f"xm/camhub/{spec.name}/info", "sensor_msgs/msg/CameraInfo", msgs.serialize(msgs.make(
                "sensor_msgs/msg/CameraInfo", header=msgs.header(t, spec.name), height=192, width=256,
                distortion_model="plumb_bob", d=np.zeros(5), k=spec.K.ravel(), r=np.eye(3).ravel(),
                p=projection(spec.K, spec.world_T_cam).ravel(), binning_x=0, binning_y=0,
                roi=msgs.make("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                              do_rectify=False))), int(t * 1e9))
        rec.write("xm/camhub/cam0/image", "sensor_msgs/msg/CompressedImage", msgs.serialize(msgs.make(
            "sensor_msgs/msg/CompressedImage", header=msgs.header(t, "cam0"), format="jpeg",
            data=np.zeros(4, np.uint8))), int(t * 1e9))
        pressure = np.zeros((16, 16), np.float32)
        pressure[2:5, 3:6] = 40.0 + f  # a press that grows over the recording
        rec.write("xm/glove/right/tactile", "xm_msgs/msg/Tactile", msgs.serialize(msgs.make(
            "xm_msgs/msg/Tactile", header=msgs.header(t, "right"), hand="right", rows=16, cols=16,
            pressure=pressure.ravel(), mask=np.ones(256, np.uint8), sequence=f)), int(t * 1e9))
    rec.close()
    return np.stack(truth)


def test_fill_gaps_interpolates_between_fits_and_holds_the_ends():
    p = np.zeros((5, N_PARAMS))
    p[1, :3], p[3, :3] = [0.0, 0.0, 0.2], [0.0, 0.0, 0.6]
    p[1, 3], p[3, 3] = 1.0, 3.0
    out = fill_gaps(p, np.array([False, True, False, True, False]))
    np.testing.assert_allclose(out[:, 3], [1.0, 1.0, 2.0, 3.0, 3.0])
    np.testing.assert_allclose(out[2, :3], [0.0, 0.0, 0.4], atol=1e-9)
    with pytest.raises(ValueError):
        fill_gaps(p, np.zeros(5, bool))


def test_offline_recon_writes_one_refined_scene_per_frame_set(tmp_path):
    src, dst = tmp_path / "rec.mcap", tmp_path / "out.mcap"
    truth = _recording(src)
    assert main([str(src), "-o", str(dst), "--detector", "simulated", "--pixel-noise", "1.5",
                 "--max-evaluations", "8"]) == 0
    scenes = [msgs.deserialize(s.data, s.msgtype) for s in read_messages(dst) if s.key == SCENE_KEY]
    assert len(scenes) == len(truth)
    hands = np.stack([np.asarray(s.hand_keypoints).reshape(-1, 3) for s in scenes])
    mask = np.stack([np.asarray(s.hand_mask) for s in scenes]).astype(bool)
    assert np.isfinite(hands).all() and mask.mean() > 0.9
    err = np.linalg.norm(hands - truth, axis=-1)[mask]
    assert err.mean() < 0.010
    kept = {s.key for s in read_messages(dst)}
    assert "xm/world/sim/truth" in kept, "the rest of the recording is copied"
    # The glove's cells ride on the refined right hand: one mesh per frame set with the whole hand.
    meshes = [msgs.deserialize(s.data, s.msgtype) for s in read_messages(dst) if s.key == MESH_KEY]
    assert len(meshes) == len(scenes), "one per frame set, as live"
    complete = sum(bool(m[KEYPOINTS_PER_HAND:].all()) for m in mask)
    assert sum(bool(len(m.hand_names)) for m in meshes) == complete > 0
    m = meshes[-1]
    assert list(m.hand_names) == ["right"]
    verts = np.asarray(m.vertices).reshape(-1, 3)
    right = hands[-1][KEYPOINTS_PER_HAND:]
    assert np.linalg.norm(verts.mean(axis=0) - right.mean(axis=0)) < 0.05, "the mesh sits on the hand"
    assert np.asarray(m.pressure).max() > 40.0, "the press shows on the mesh"


def test_offline_recon_refuses_a_recording_without_cameras(tmp_path, capsys):
    src = tmp_path / "empty.mcap"
    McapRecorder(src).close()
    assert main([str(src), "-o", str(tmp_path / "out.mcap"), "--detector", "simulated"]) == 2
    assert "CameraInfo" in capsys.readouterr().err


def test_offline_recon_refuses_a_blend_outside_zero_to_one(tmp_path, capsys):
    src = tmp_path / "empty.mcap"
    McapRecorder(src).close()
    assert main([str(src), "-o", str(tmp_path / "out.mcap"), "--blend", "1.5"]) == 2
    assert "--blend 1.5 must lie between 0 and 1" in capsys.readouterr().err


def _image_recording(path, frames: int = 3) -> None:
    """Every camera's JPEG per frame set (cam2's corrupt in the first), no truth."""
    rec = McapRecorder(path)
    ok, jpeg = cv2.imencode(".jpg", np.full((192, 256, 3), 80, np.uint8))
    for f in range(frames):
        t = 50.0 + 0.2 * f
        for spec in camera_specs(256, 192):
            rec.write(f"xm/camhub/{spec.name}/info", "sensor_msgs/msg/CameraInfo", msgs.serialize(msgs.make(
                "sensor_msgs/msg/CameraInfo", header=msgs.header(t, spec.name), height=192, width=256,
                distortion_model="plumb_bob", d=np.zeros(5), k=spec.K.ravel(), r=np.eye(3).ravel(),
                p=projection(spec.K, spec.world_T_cam).ravel(), binning_x=0, binning_y=0,
                roi=msgs.make("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                              do_rectify=False))), int(t * 1e9))
            data = b"\xff\xd8broken" if (f == 0 and spec.name == "cam2") else jpeg.tobytes()
            rec.write(f"xm/camhub/{spec.name}/image", "sensor_msgs/msg/CompressedImage", msgs.serialize(msgs.make(
                "sensor_msgs/msg/CompressedImage", header=msgs.header(t, spec.name), format="jpeg",
                data=np.frombuffer(data, np.uint8))), int(t * 1e9))
    rec.close()


def test_offline_recon_with_the_learned_detector_reads_images_only(tmp_path, monkeypatch, capsys):
    rng = np.random.default_rng(5)
    hands = rng.uniform(-0.04, 0.04, (2, 21, 3)) + [[[-0.1, 0.0, 0.06]], [[0.1, 0.0, 0.06]]]  # hand-sized, apart
    points = np.concatenate([hands.reshape(-1, 3), rng.uniform([-0.1, -0.1, 0.0], [0.1, 0.1, 0.1], (8, 3))])

    class LearnedDetector:
        def detect(self, views):
            uv, _ = project(np.stack([v.model.P for v in views]), points)
            return uv, np.ones(uv.shape[:2])

    module = types.ModuleType("services.recon.learned_detector")
    module.LearnedDetector = LearnedDetector
    monkeypatch.setitem(sys.modules, "services.recon.learned_detector", module)
    src, dst = tmp_path / "rec.mcap", tmp_path / "out.mcap"
    _image_recording(src)
    assert main([str(src), "-o", str(dst), "--detector", "learned", "--no-refine"]) == 0
    assert "1 corrupt JPEG" in capsys.readouterr().out
    scenes = [msgs.deserialize(s.data, s.msgtype) for s in read_messages(dst) if s.key == SCENE_KEY]
    assert len(scenes) == 3
    assert list(scenes[0].object_names) == task_keypoint_names("assembly")
    np.testing.assert_allclose(np.asarray(scenes[0].hand_keypoints).reshape(-1, 3), points[:42], atol=1e-3)


def test_offline_recon_without_a_learned_detector_says_how_to_train(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "services.recon.learned_detector", None)
    src = tmp_path / "rec.mcap"
    _image_recording(src, frames=1)
    assert main([str(src), "-o", str(tmp_path / "out.mcap"), "--detector", "learned"]) == 2
    assert "xm detector train" in capsys.readouterr().err


def _teacher_frames(frames: int, swap_from: int) -> tuple[Frames, np.ndarray]:
    """Simulated detections of a teacher session (every camera, no noise) whose cam0 exchanges the
    left and right hands' channels from frame set ``swap_from`` on; and the truth (T,42,3)."""
    sim = WorldSim("assembly", seed=7311)
    specs = camera_specs(256, 192)
    P = np.stack([projection(s.K, s.world_T_cam) for s in specs])
    out = Frames(cameras={s.name: CameraModel(P[i], 256, 192) for i, s in enumerate(specs)})
    truth = []
    for f in range(frames):
        sim.step(100)
        hands = sim.hand_keypoints().reshape(-1, 3)
        _, objects = sim.object_keypoints()
        uv, _ = project(P, np.concatenate([hands, objects]))
        if f >= swap_from:
            uv[0, :KEYPOINTS_PER_HAND], uv[0, KEYPOINTS_PER_HAND:2 * KEYPOINTS_PER_HAND] = \
                uv[0, KEYPOINTS_PER_HAND:2 * KEYPOINTS_PER_HAND].copy(), uv[0, :KEYPOINTS_PER_HAND].copy()
        out.stamps.append(0.2 * f)
        out.uv.append(uv)
        out.confidence.append(np.ones(uv.shape[:2]))
        truth.append(hands)
    return out, np.stack(truth)


def test_the_refinement_sees_each_detection_on_the_hand_it_was_assigned_to(monkeypatch):
    frames, truth = _teacher_frames(14, swap_from=10)
    seen = {}

    def spy(shape, side, P, uv, confidence, init, have, config):
        seen[side] = (uv, confidence)
        return init.copy(), {}
    monkeypatch.setattr(cli, "refine_hand", spy)
    result = cli.refine_hands(frames, "assembly", OfflineConfig())
    P = np.stack([m.P for m in frames.cameras.values()])
    assert set(seen) == {"left", "right"}
    for h, side in enumerate(("left", "right")):
        uv, conf = seen[side]
        first = np.flatnonzero(result.refined[:, h])[0]
        sl = slice(h * KEYPOINTS_PER_HAND, (h + 1) * KEYPOINTS_PER_HAND)
        true_uv, _ = project(P, truth[first:first + len(uv), sl])  # (C,T,21,2)
        used = conf > 0
        assert used[10 - first:, 0].any(), "cam0's swapped detections are used, on their own hand"
        err = np.linalg.norm(uv - true_uv.transpose(1, 0, 2, 3), axis=-1)[used]
        assert err.max() < 1e-6, "every detection the refinement sees belongs to its hand"


def test_segments_split_at_a_gap_the_hand_could_not_have_crossed():
    wrist = np.zeros((8, 3))
    wrist[5:, 0] = 0.5  # 0.5 m between frames 3 and 5 (0.4 s): a reset, not a motion
    have = np.array([True, True, False, True, False, True, True, True])
    stamps = 0.2 * np.arange(8)
    parts = segments(wrist, have, stamps)
    assert [list(p) for p in parts] == [[0, 1, 2, 3], [5, 6, 7]], "the slow gap (frame 2) is filled"
    assert len(segments(wrist, have, stamps, max_speed=2.0)) == 1
    assert segments(wrist, np.zeros(8, bool), stamps) == []


def _moved_hand_frames(frames: int, jump_at: int) -> tuple[Frames, np.ndarray]:
    """Noise-free detections of a teacher session whose right hand is unseen in frame set
    ``jump_at`` and 0.4 m away from there on (a demonstration reset); and the truth (T,42,3)."""
    frames_, _ = _teacher_frames(frames, swap_from=frames)
    sim = WorldSim("assembly", seed=7311)
    P = np.stack([m.P for m in frames_.cameras.values()])
    truth = []
    sl = slice(KEYPOINTS_PER_HAND, 2 * KEYPOINTS_PER_HAND)
    for f in range(frames):
        sim.step(100)
        hands = sim.hand_keypoints().reshape(-1, 3)
        _, objects = sim.object_keypoints()
        if f >= jump_at:
            hands[sl] += [0.0, 0.4, 0.0]
        frames_.uv[f] = project(P, np.concatenate([hands, objects]))[0]
        if f == jump_at:
            frames_.confidence[f][:, sl] = 0.0
        truth.append(hands)
    return frames_, np.stack(truth)


def test_the_refinement_does_not_interpolate_a_hand_across_a_reset():
    frames, truth = _moved_hand_frames(16, jump_at=8)
    result = cli.refine_hands(frames, "assembly", OfflineConfig(max_nfev=5))
    right = result.hands[:, 1]
    assert not result.hand_mask[8, 1].any(), "the frame set between the places is not seen: masked"
    assert result.summary["right"]["segments"] == 2
    err = np.linalg.norm(right - truth[:, KEYPOINTS_PER_HAND:], axis=-1)
    seen = result.hand_mask[:, 1].astype(bool)
    assert seen[[6, 7, 9, 10]].all() and err[seen].max() < 0.01


def test_the_offline_shape_comes_from_every_confident_frame():
    """A recording whose first frame sets see the right hand's fingers 20 % short (a biased start):
    the shape the refinement uses is the whole recording's, not the first 8 frame sets'."""
    frames, truth = _teacher_frames(30, swap_from=30)
    P = np.stack([m.P for m in frames.cameras.values()])
    sl = slice(KEYPOINTS_PER_HAND, 2 * KEYPOINTS_PER_HAND)
    for f in range(8):
        right = truth[f, sl]
        short = right.copy()
        for chain in CHAINS:  # each bone 20 % shorter, from the chain's base outward
            for a, b in zip(chain[:-1], chain[1:], strict=True):
                short[b] = short[a] + 0.8 * (right[b] - right[a])
        frames.uv[f][:, sl] = project(P, short)[0]
    result = cli.refine_hands(frames, "assembly", OfflineConfig(), refine=False)
    true_bones = np.linalg.norm(np.diff(truth[:, sl][:, CHAINS], axis=2), axis=-1).mean(axis=0)
    np.testing.assert_allclose(result.shapes["right"].bones[1:], true_bones[1:], rtol=0.05)


def test_a_frame_without_a_live_fit_reports_only_what_was_seen_there():
    frames, truth = _teacher_frames(14, swap_from=14)
    sl = slice(KEYPOINTS_PER_HAND, 2 * KEYPOINTS_PER_HAND)
    frames.confidence[8][:, KEYPOINTS_PER_HAND:KEYPOINTS_PER_HAND + 16] = 0.0  # 5 keypoints left: no fit
    result = cli.refine_hands(frames, "assembly", OfflineConfig(max_nfev=5))
    assert result.refined[8, 1] and result.summary["right"]["segments"] == 1, "the gap is refined, not split"
    np.testing.assert_array_equal(result.hand_mask[8, 1], np.r_[np.zeros(16), np.ones(5)])
    np.testing.assert_array_equal(result.hands[8, 1, :16], 0.0)
    err = np.linalg.norm(result.hands[8, 1, 16:] - truth[8, sl][16:], axis=-1)
    assert err.max() < 0.01
    assert result.hand_mask[[7, 9], 1].all(), "frames the live fit held report every keypoint"
