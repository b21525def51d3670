"""`xm recon REC.mcap -o OUT.mcap`: reconstruct a whole recording offline.

The live stages run over every frame set of the recording twice (the second time with each hand's
shape learned from every confident frame of the first pass, so no frame waits for the
initialisation phase and the shape averages the whole recording's noise), then
each hand's trajectory is refined as one problem (services/recon/offline.py): robust reprojection
against the detections the live triangulation kept (as it took them, each on the hand it was
assigned to), joint limits, a jerk regulariser, gaps filled from interpolated poses where the hand
could have crossed them (a hand that left and came back elsewhere is not interpolated). OUT.mcap
holds the recording with `xm/recon/main/scene` replaced by the refined scenes and
`xm/recon/main/tactile_mesh` by the glove's cells on the refined hands.
"""

from __future__ import annotations

import argparse
import bisect
import importlib
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.glove.layout import region_means
from services.recon.detector import CameraModel, SimulatedDetector, View, readout_window
from services.recon.frameset import FrameSetBuffer
from services.recon.hand_fit import FitConfig, fuse
from services.recon.hand_model import N_PARAMS, forward
from services.recon.offline import OfflineConfig, refine_hand, segments
from services.recon.pipeline import Reconstructor
from services.recon.scene import scene_message, tactile_matrix
from services.recon.service import TACTILE_MAX_AGE_S, TRAIN_HINT, decode_window, info_key
from services.recon.tactile_projection import MSGTYPE as MESH_MSGTYPE
from services.recon.tactile_projection import TactileProjector
from services.recorder.writer import McapRecorder, RecordingError, read_messages
from shared import msgs
from shared.demo import KEYPOINTS_PER_HAND
from shared.ports import CAMERAS

SCENE_KEY = "xm/recon/main/scene"
MESH_KEY = "xm/recon/main/tactile_mesh"


@dataclass
class Frames:
    """Per frame set: stamp, detections (C,N,2) and confidences (C,N) in CAMERAS order."""

    cameras: dict[str, CameraModel] = field(default_factory=dict)
    stamps: list[float] = field(default_factory=list)
    uv: list[np.ndarray] = field(default_factory=list)
    confidence: list[np.ndarray] = field(default_factory=list)
    object_names: list[str] | None = None
    tactile: dict[str, list[tuple[float, np.ndarray]]] = field(default_factory=dict)  # region means
    pressure: dict[str, list[tuple[float, np.ndarray]]] = field(default_factory=dict)  # 16x16 frames
    corrupt: int = 0  # JPEG windows that did not decode
    hand_present_confidence: float = 0.0  # the detector's (LearnedDetector.hand_present_confidence)


def _camera(key: str) -> str:
    return key.split("/")[2]


def read_detections(path: Path, args: argparse.Namespace, n_points: int) -> Frames:
    """Detections per frame set of a recording: the simulated detector on the recorded truth, or the
    learned detector on the recorded JPEG windows."""
    out = Frames()
    truth: list[tuple[float, object]] = []
    triggers: list[float] = []
    buffer, images = FrameSetBuffer(), []
    learned = _learned(args) if args.detector == "learned" else None
    out.hand_present_confidence = getattr(learned, "hand_present_confidence", 0.0)
    # every camera the recording has, so that its first frame set is not cut short
    cameras = {_camera(s.key) for s in read_messages(path, keys={f"xm/camhub/{c}/info" for c in CAMERAS})}
    expected = cameras | {info_key(c) for c in cameras}
    for stored in read_messages(path):
        if stored.key.endswith("/info") and stored.key.startswith("xm/camhub/"):
            msg = msgs.deserialize(stored.data, stored.msgtype)
            model = CameraModel(np.asarray(msg.p, float).reshape(3, 4), msg.width, msg.height, readout_window(msg))
            out.cameras[_camera(stored.key)] = model
            if learned is not None:  # each image is read with the window of its own frame set
                images += buffer.add(msgs.stamp_seconds(msg.header.stamp), info_key(_camera(stored.key)), model,
                                     expected)
        elif stored.key == "xm/world/sim/truth" and learned is None:
            msg = msgs.deserialize(stored.data, stored.msgtype)
            truth.append((msgs.stamp_seconds(msg.header.stamp), msg))
        elif stored.key.startswith("xm/camhub/") and stored.key.endswith("/image"):
            msg = msgs.deserialize(stored.data, stored.msgtype)
            stamp = msgs.stamp_seconds(msg.header.stamp)
            if learned is None:
                if _camera(stored.key) == CAMERAS[0]:
                    triggers.append(stamp)
            else:
                images += buffer.add(stamp, _camera(stored.key), bytes(msg.data), expected)
        elif stored.key.startswith("xm/glove/") and stored.key.endswith("/tactile"):
            msg = msgs.deserialize(stored.data, stored.msgtype)
            pressure = np.asarray(msg.pressure, np.float32).reshape(msg.rows, msg.cols)
            out.tactile.setdefault(msg.hand, []).append((msgs.stamp_seconds(msg.header.stamp),
                                                         region_means(pressure)))
            out.pressure.setdefault(msg.hand, []).append((msgs.stamp_seconds(msg.header.stamp), pressure))
    images += buffer.flush()
    order = [c for c in CAMERAS if c in out.cameras]
    if len(order) < 2:
        raise RecordingError(f"{path}: CameraInfo of fewer than two cameras; nothing to triangulate")
    if learned is None:
        if not truth:
            raise RecordingError(f"{path}: no xm/world/sim/truth for the simulated detector (use --detector learned)")
        det = SimulatedDetector(args.pixel_noise, args.dropout, args.seed, args.outliers)
        truth_stamps = [s for s, _ in truth]
        for stamp in triggers:
            i = min(bisect.bisect_left(truth_stamps, stamp), len(truth) - 1)
            if i > 0 and abs(truth_stamps[i - 1] - stamp) < abs(truth_stamps[i] - stamp):
                i -= 1
            msg = truth[i][1]
            points = np.concatenate([np.asarray(msg.hand_keypoints, float).reshape(-1, 3),
                                     np.asarray(msg.object_keypoints, float).reshape(-1, 3)])
            visible = np.concatenate([np.asarray(msg.hand_visible), np.asarray(msg.object_visible)]) \
                if len(msg.hand_visible) else None
            uv, seen = det.detect([out.cameras[c] for c in order], points, visible)
            out.object_names = list(msg.object_names)
            _append(out, stamp, uv, seen.astype(float))
    else:
        for stamp, blobs in images:
            views = []
            for c in (c for c in order if c in blobs and info_key(c) in blobs):
                img = decode_window(blobs[c], blobs[info_key(c)])
                if img is None:
                    out.corrupt += 1  # dropped, like the live service does
                else:
                    views.append(View(c, blobs[info_key(c)], img))
            if len(views) < 2:
                continue
            uv, conf = learned.detect(views)
            if uv.shape != (len(views), n_points, 2):
                raise RecordingError(f"the detector returned {uv.shape}, expected ({len(views)}, {n_points}, 2)")
            full_uv, full_conf = np.zeros((len(order), n_points, 2)), np.zeros((len(order), n_points))
            for v, view in enumerate(views):
                full_uv[order.index(view.camera)], full_conf[order.index(view.camera)] = uv[v], conf[v]
            _append(out, stamp, full_uv, full_conf)
    return out


def _append(out: Frames, stamp: float, uv: np.ndarray, conf: np.ndarray) -> None:
    out.stamps.append(stamp)
    out.uv.append(uv)
    out.confidence.append(conf)


def _learned(args: argparse.Namespace) -> object:
    try:
        # Imported here: the network's runtime is needed only for this detector.
        cls = importlib.import_module("services.recon.learned_detector").LearnedDetector
        return cls(args.weights) if args.weights else cls()
    except (ImportError, AttributeError, FileNotFoundError, OSError, ValueError) as exc:
        raise RecordingError(f"learned detector unavailable ({exc}); {TRAIN_HINT}") from exc


@dataclass
class OfflineHands:
    """The offline hands before the scenes: the second live pass per frame set, the hands (T,H,21,3)
    with their mask (T,H,21), and which frames of each hand the refinement produced (T,H)."""
    live: list
    hand_names: list[str]
    object_names: list[str]
    hands: np.ndarray
    hand_mask: np.ndarray
    refined: np.ndarray
    summary: dict
    shapes: dict  # per hand, the HandShape the refinement used (None: never initialised)


def refine_hands(frames: Frames, task: str, config: OfflineConfig, refine: bool = True) -> OfflineHands:
    """The two live passes (the first estimates each hand's shape from every confident frame),
    then each hand's trajectory refined over the segments it was seen (``offline.segments``),
    against the detections the live triangulation kept (as it took them: after the hand channels
    were reassigned to the hand each detection belongs to)."""
    order = [c for c in CAMERAS if c in frames.cameras]
    P = np.stack([frames.cameras[c].P for c in order])
    # The first pass collects every confident frame of the recording and estimates each hand's
    # shape from all of them (the live phase takes its first 8, whose noise the shape keeps).
    first = Reconstructor(task, object_names=frames.object_names,
                          hand_present_confidence=frames.hand_present_confidence,
                          fit=FitConfig(init_frames=len(frames.stamps) + 1))
    for uv, conf in zip(frames.uv, frames.confidence, strict=True):
        first.step(P, uv, conf)
    second = Reconstructor(task, object_names=frames.object_names,
                           hand_present_confidence=frames.hand_present_confidence)
    for name, tracker in second.trackers.items():
        if first.trackers[name].finish_initialisation(FitConfig().init_frames):
            tracker.shape = first.trackers[name].shape
    T, H = len(frames.stamps), len(second.hand_names)
    stamps = np.asarray(frames.stamps, float)
    live = []
    params = np.zeros((H, T, N_PARAMS))
    have = np.zeros((H, T), bool)
    kept = np.zeros((T,) + frames.confidence[0].shape)
    uv_all = np.zeros((T,) + frames.uv[0].shape)
    for t, (uv, conf) in enumerate(zip(frames.uv, frames.confidence, strict=True)):
        r = second.step(P, uv, conf)
        live.append(r)
        # The detections the live triangulation kept, as it took them: a hand channel the identity
        # step swapped holds the other hand's detection in the recorded arrays.
        uv_all[t], kept[t] = r.uv, r.confidence * r.inliers
        for h, tracker in enumerate(second.trackers.values()):
            if tracker.last_params is not None:
                params[h, t], have[h, t] = tracker.last_params, True
    summary = {}
    hands = np.stack([r.hands for r in live])  # (T,H,21,3)
    hand_mask = np.stack([r.hand_mask for r in live])
    refined = np.zeros((T, H), bool)
    for h, (name, tracker) in enumerate(second.trackers.items()):
        if not refine or tracker.shape is None or have[h].sum() < 4:
            summary[name] = {"refined": False, "live_fits": int(have[h].sum())}
            continue
        sl = slice(h * KEYPOINTS_PER_HAND, (h + 1) * KEYPOINTS_PER_HAND)
        parts = segments(params[h, :, 3:6], have[h], stamps, config.max_gap_speed_m_s)
        infos = []
        for span in parts:  # frames between segments keep the live pass's result
            out, info = refine_hand(tracker.shape, name, P, uv_all[span][:, :, sl], kept[span][:, :, sl],
                                    params[h, span], have[h, span], config)
            for i, t in enumerate(span):
                r = live[t]
                seen = r.inliers[:, sl].sum(axis=0) >= 2
                hands[t, h] = fuse(forward(tracker.shape, out[i], name), r.triangulated[sl], seen, config.blend)
                # A frame the live fit did not hold (a gap, a refused fit) reports what was seen there:
                # the model's fill-ins of its unseen keypoints are 20-34 mm off on held-out sessions.
                hand_mask[t, h] = 1 if have[h, t] else seen
                hands[t, h] *= hand_mask[t, h][:, None]
            refined[span, h] = True
            infos.append(info)
        summary[name] = {"refined": True, "segments": len(parts),
                         **{k: [i[k] for i in infos] for k in infos[0]}}  # per segment
    return OfflineHands(live, second.hand_names, second.object_names, hands, hand_mask, refined, summary,
                        {name: tracker.shape for name, tracker in second.trackers.items()})


def reconstruct(frames: Frames, task: str, config: OfflineConfig, refine: bool = True) -> tuple[list, dict]:
    """Scenes (one per frame set) and a summary per hand."""
    result = refine_hands(frames, task, config, refine)
    hands = result.hands
    scenes = []
    for t, stamp in enumerate(frames.stamps):
        tactile, tactile_mask = tactile_matrix(result.hand_names, nearest(frames.tactile, stamp))
        r = result.live[t]
        scenes.append(scene_message(stamp, result.hand_names, hands[t], result.hand_mask[t], result.object_names,
                                    r.objects, r.object_mask, tactile, tactile_mask))
    return scenes, result.summary


def nearest(series: dict[str, list[tuple[float, np.ndarray]]], stamp: float) -> dict[str, np.ndarray]:
    """Per hand, the sample of its (stamp, value) series nearest ``stamp``, when within
    TACTILE_MAX_AGE_S."""
    fresh = {}
    for hand, samples in series.items():
        near = min(samples, key=lambda s: abs(s[0] - stamp))
        if abs(near[0] - stamp) < TACTILE_MAX_AGE_S:
            fresh[hand] = near[1]
    return fresh


def tactile_meshes(frames: Frames, scenes: list) -> tuple[list, dict[str, int]]:
    """The glove's cells on the reconstructed hands (services/recon/tactile_projection.py), one
    TactileMesh per frame set as live recon publishes them (no hands where no gloved hand has all
    its keypoints); and per reason, the hands left out."""
    projector, out, skipped = TactileProjector(), [], {}
    for scene in scenes:
        stamp = msgs.stamp_seconds(scene.header.stamp)
        names = list(scene.hand_names)
        hands = np.asarray(scene.hand_keypoints, float).reshape(len(names), KEYPOINTS_PER_HAND, 3)
        mask = np.asarray(scene.hand_mask, np.uint8).reshape(len(names), KEYPOINTS_PER_HAND)
        msg, why = projector.message(stamp, names, hands, mask, nearest(frames.pressure, stamp))
        for reason in why.values():
            skipped[reason] = skipped.get(reason, 0) + 1
        out.append(msg)
    return out, skipped


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="xm recon", description=__doc__.splitlines()[0])
    parser.add_argument("recording", type=Path, help="an MCAP recording with camhub's frames (xm record)")
    parser.add_argument("-o", "--out", type=Path, required=True, help="where to write the reconstructed copy")
    parser.add_argument("--task", default="assembly", help="names the object keypoints (default: %(default)s)")
    parser.add_argument("--detector", choices=("learned", "simulated"), default="learned",
                        help="learned: the shipped network on the recorded images (default); simulated: the "
                             "recorded truth projected (an experiment)")
    parser.add_argument("--weights", default="", help="the learned detector's weights (default: its own)")
    parser.add_argument("--pixel-noise", type=float, default=1.0)
    parser.add_argument("--dropout", type=float, default=0.08)
    parser.add_argument("--outliers", type=float, default=0.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-refine", action="store_true", help="the live stages only (two passes)")
    parser.add_argument("--jerk", type=float, default=OfflineConfig.jerk_px_per_m,
                        help="weight of the keypoints' jerk, px per metre of third difference "
                             "(default: %(default)s)")
    parser.add_argument("--max-evaluations", type=int, default=OfflineConfig.max_nfev,
                        help="of the trajectory refinement per hand (default: %(default)s)")
    parser.add_argument("--blend", type=float, default=OfflineConfig.blend,
                        help="a refined keypoint's share of its triangulated position, 0 (the hand model alone) to 1 "
                             "(default: %(default)s)")
    args = parser.parse_args(argv)
    if not 0.0 <= args.blend <= 1.0:
        print(f"xm recon: --blend {args.blend} must lie between 0 and 1", file=sys.stderr)
        return 2
    if args.out.resolve() == args.recording.resolve():
        print("xm recon: OUT must differ from the recording", file=sys.stderr)
        return 2
    try:
        frames = read_detections(args.recording, args, Reconstructor(args.task).n_points)
        if not frames.stamps:
            raise RecordingError(f"{args.recording}: no frame sets (no camhub images)")
        config = OfflineConfig(jerk_px_per_m=args.jerk, max_nfev=args.max_evaluations, blend=args.blend)
        scenes, summary = reconstruct(frames, args.task, config, refine=not args.no_refine)
        meshes, mesh_skipped = tactile_meshes(frames, scenes)
    except (RecordingError, ValueError) as exc:
        print(f"xm recon: {exc}", file=sys.stderr)
        return 2
    rec = McapRecorder(args.out, metadata={"source": str(args.recording), "recon": "offline"})
    for stored in read_messages(args.recording):
        if not stored.key.startswith("xm/recon/"):
            rec.write(stored.key, stored.msgtype, stored.data, stored.log_time)
    for scene in scenes:
        stamp_ns = int(round(msgs.stamp_seconds(scene.header.stamp) * 1e9))
        rec.write(SCENE_KEY, "xm_msgs/msg/Scene", msgs.serialize(scene, "xm_msgs/msg/Scene"), stamp_ns)
    for mesh in meshes:
        stamp_ns = int(round(msgs.stamp_seconds(mesh.header.stamp) * 1e9))
        rec.write(MESH_KEY, MESH_MSGTYPE, msgs.serialize(mesh, MESH_MSGTYPE), stamp_ns)
    rec.close()
    print(f"xm recon: {len(scenes)} frame sets -> {args.out}"
          + (f" ({frames.corrupt} corrupt JPEG windows dropped)" if frames.corrupt else ""))
    print(f"  tactile meshes: {len(meshes)}" + (f" (hands left out: {mesh_skipped})" if mesh_skipped else ""))
    for hand, info in summary.items():
        print(f"  {hand}: {info}")
    return 0
