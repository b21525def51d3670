"""recon node: on each synchronized frame set, detect 2-D keypoints per camera, reconstruct them
in 3-D (robust triangulation, articulated hand fit, rigid objects; services/recon/pipeline.py) and
publish the scene with the latest tactile region pressures of each glove, and each gloved hand's
surface mesh with the glove's pressure projected onto it (services/recon/tactile_projection.py).

Two detectors: ``learned`` (the default) decodes every camera's JPEG window and runs the trained
network (services/recon/learned_detector.py, imported only when chosen; the weights ship in
models/detector/); ``simulated`` projects the simulator's truth on the first camera's image of
each set, an option for experiments and the only one that subscribes to the truth.

The glove's layout (region means, the tactile projection) is its cell map, the ``cellmap``
parameter (services/glove/layout.py; empty: the shipped one). A cell map that cannot be used is
refused at start: recon publishes scenes without tactile data and no tactile meshes, its status
is ``degraded`` with the file and the problem, and ``bad_cellmap`` is counted."""

from __future__ import annotations

import collections
import importlib
import time
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np

from services.glove import layout as glove_layout
from services.glove.layout import CellMapError
from services.recon.detector import CameraModel, SimulatedDetector, View, readout_window
from services.recon.frameset import FrameSetBuffer
from services.recon.pipeline import Reconstruction, Reconstructor
from services.recon.scene import scene_message, tactile_matrix
from services.recon.tactile_projection import TactileProjector
from shared import msgs
from shared.demo import KEYPOINTS_PER_HAND
from shared.realtime import raise_cpu_share
from shared.runtime import Node

TACTILE_MAX_AGE_S = 0.5
# Released frame sets waiting for detection: one beside the newest absorbs a single slow detection
# (a busy host) without skipping a set; a recon slower than the cameras for longer skips the oldest.
WAITING_SETS = 2
INFO_SUFFIX = "/info"


def info_key(camera: str) -> str:
    """A frame set's entry for a camera's CameraInfo, beside its image's entry (the camera's name)."""
    return camera + INFO_SUFFIX
DETECTORS = ("simulated", "learned")
TRAIN_HINT = "regenerate it with `make detector` (xm detector label, xm detector train; docs/perception.md)"


def keypoint_names(recon: Reconstructor) -> list[str]:
    """The detector channels recon expects: ``hand/0..20`` per hand, then the task's object keypoints."""
    return [f"{h}/{k}" for h in recon.hand_names for k in range(KEYPOINTS_PER_HAND)] + list(recon.object_names)


def decode_window(data: bytes, model: CameraModel) -> np.ndarray | None:
    """RGB image of a JPEG readout window, or None when it does not decode to the window's size."""
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        return None
    _, _, w, h = model.roi or (0, 0, model.width, model.height)
    if img.shape[:2] != (h, w):
        return None
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


class ReconService:
    @dataclass
    class Params:
        detector: str = "learned"  # the trained network on the images; "simulated": projected truth (experiments)
        task: str = "assembly"  # its object keypoints name the scene's objects (learned detector)
        weights: str = ""  # the learned detector's weights; empty: its own default path
        precision: str = "auto"  # its graphs: the int8 copies where they match (auto), "int8" or "float32"
        pixel_noise: float = 1.0  # simulated detector
        dropout: float = 0.08
        outliers: float = 0.0
        seed: int = 0
        gate_px: float = 6.0  # reprojection gate of the robust triangulation
        fit_hands: bool = True  # articulated hand model (else the triangulated keypoints)
        cellmap: str = ""  # the glove's cell map, as the glove service's; empty: models/skin/glove_cellmap.json
        # On a busy host recon runs this many nice values ahead of the other services (as the world
        # does): it needs the most CPU of the cell, and a starved recon leaves the scene over 1 s old.
        cpu_share_boost: int = 5

    _prepared: ClassVar[dict[str, object]] = {}  # a standby spare's loaded network, by its params

    @classmethod
    def prepare(cls, params: Params) -> None:
        """A standby spare imports and loads the learned detector before it takes over (most of
        recon's start); a failure is left to the real start, which reports it."""
        if params.detector == "learned":
            cls._prepared[repr(params)] = cls._new_detector(params)

    @staticmethod
    def _new_detector(params: Params) -> object:
        # Imported here: torch/onnx stay out of the simulated path and of builds without them.
        module = importlib.import_module("services.recon.learned_detector")
        cls = module.LearnedDetector
        return cls(params.weights, precision=params.precision) if params.weights else cls(precision=params.precision)

    def __init__(self, node: Node, params: Params) -> None:
        if params.detector not in DETECTORS:
            raise ValueError(f"recon detector {params.detector!r}: choose one of {', '.join(DETECTORS)}")
        self.node = node
        self.params = params
        self.cameras: dict[str, CameraModel] = {}
        self.truth: collections.deque = collections.deque(maxlen=64)  # (stamp, msg)
        self.tactile: dict[str, tuple[float, np.ndarray]] = {}
        self.pressure: dict[str, tuple[float, np.ndarray]] = {}  # the newest 16x16 frame per glove
        self.layout, self.projector, self.layout_error = None, None, ""
        try:
            self.layout = glove_layout.load(params.cellmap)
            self.projector = TactileProjector(layout=self.layout)
        except CellMapError as exc:
            self.layout_error = str(exc)
            node.stats.count("bad_cellmap")
            node.log.error("%s; recon publishes no tactile data", exc)
        self.times: collections.deque = collections.deque(maxlen=200)  # per-stage seconds per frame set
        self.frame_sets = 0
        self.recon: Reconstructor | None = None
        self.learned = None
        self.scene_pub = node.output("scene")
        self.mesh_pub = node.output("tactile_mesh")
        node.health_extra = self._health
        self.info_subs = node.input("info", self.on_info)
        if self.layout is not None:
            node.input("tactile", self.on_tactile)
        if params.detector == "simulated":
            self.simulated = SimulatedDetector(params.pixel_noise, params.dropout, params.seed, params.outliers)
            node.input("truth", self.on_truth)
            node.input("frame", self.on_frame)  # the first camera's image marks a triggered frame set
        else:
            self.recon = Reconstructor(params.task, gate_px=params.gate_px, fit_hands=params.fit_hands)
            self.learned = self._load_learned()
            self.recon.hand_present_confidence = getattr(self.learned, "hand_present_confidence", 0.0)
            # Images and CameraInfos come through separate subscriptions, whose handlers may run a
            # frame set apart under load: a set is released incomplete only once two newer ones began.
            self.buffer = FrameSetBuffer(late_after=2)
            self.ready: collections.deque[tuple[float, dict]] = collections.deque()  # released, not yet detected
            self.frame_sets_behind = 0  # released sets skipped: newer ones filled the waiting line first
            if self.learned is not None:
                self.images_key = node.input("image", self.on_image)[0].key_expr  # its failures are counted under it
                node.set_status("ok")
        if params.cpu_share_boost > 0:
            raise_cpu_share("recon", node.log, params.cpu_share_boost)
        if self.layout_error and node.status != "error":
            node.set_status("degraded", f"{self.layout_error}: no tactile data")

    def _load_learned(self) -> object | None:
        """The learned detector, or None (status says how to get it) when its module or weights are
        missing: recon then publishes nothing rather than wrong scenes."""
        try:
            detector = self._prepared.pop(repr(self.params), None) or self._new_detector(self.params)
        except (ImportError, AttributeError) as exc:
            msg = f"learned detector unavailable ({exc}); {TRAIN_HINT}"
        except (FileNotFoundError, OSError, ValueError) as exc:
            msg = f"learned detector weights missing or unreadable ({exc}); {TRAIN_HINT}"
        else:
            expected = keypoint_names(self.recon)
            if list(detector.names) == expected:
                for stem, said in getattr(detector, "precision", {}).items():
                    if said not in ("int8", "float32"):  # a stand-in for the int8 graph, with why
                        self.node.log.warning("detector graph %s runs as %s", stem, said)
                return detector
            msg = (f"the learned detector's {len(detector.names)} keypoints are not task {self.params.task!r}'s "
                   f"{len(expected)} in recon's order (weights of another task?); {TRAIN_HINT}")
        self.node.stats.count("detector_unavailable")
        self.node.log.error(msg)
        self.node.set_status("error", msg)
        return None

    def _health(self) -> dict:
        t = list(self.times)
        keys = dict.fromkeys(k for x in t for k in x)  # a stage may run in some frame sets only
        stages = {k: round(1000 * float(np.median([x[k] for x in t if k in x])), 2) for k in keys}
        out = {"detector": self.params.detector, "frame_sets": self.frame_sets, "stage_ms_median": stages,
               "layout": self.layout.summary() if self.layout is not None else {"error": self.layout_error}}
        if self.recon is not None:
            out["hand_resets"] = {h: tr.resets for h, tr in self.recon.trackers.items()}
            out["hands_seen_twice"] = self.recon.hands_seen_twice
            out["hand_keypoints_beyond_the_hand"] = self.recon.beyond_hand
            out["hand_detections_swapped"] = self.recon.hand_swaps
            out["hand_detections_dropped"] = self.recon.hand_detections_dropped
            out["hand_views_absent"] = self.recon.hand_views_absent
            out["object_detections_off_track"] = self.recon.object_detections_dropped
            out["object_detections_outside_window"] = self.recon.objects_outside_windows
            out["objects_unconfirmed"] = self.recon.objects_unconfirmed
            out["hand_shape_estimated"] = {h: tr.shape is not None for h, tr in self.recon.trackers.items()}
        if self.params.detector == "learned" and self.learned is not None:
            out["detector_precision"] = getattr(self.learned, "precision", {})  # per graph, why when not int8
            out["partial_frame_sets"] = self.buffer.released_partial
            out["frame_sets_behind"] = self.frame_sets_behind
            out["late_images"] = self.buffer.dropped_stale
            out["timeline_restarts"] = self.buffer.restarts
            out["object_crops"] = getattr(self.learned, "object_crops", 0)  # a detector without an object stage
            out["object_crops_missed"] = getattr(self.learned, "object_crops_missed", 0)  # too weak to show it
            out["object_crops_unsteady"] = getattr(self.learned, "object_crops_unsteady", 0)  # peaks followed the crop
            schedule = getattr(self.learned, "schedule", None)  # untouched objects kept where their crops placed them
            out["objects_kept_in_place"] = getattr(schedule, "kept_in_place", 0)
        return out

    def on_info(self, msg, key: str) -> None:
        camera = key.split("/")[2]
        model = CameraModel(np.asarray(msg.p, float).reshape(3, 4), msg.width, msg.height, readout_window(msg))
        self.cameras[camera] = model
        if self.learned is not None:
            # The window moves every frame set: each image is read with the CameraInfo of its own stamp.
            self._add(msgs.stamp_seconds(msg.header.stamp), info_key(camera), model)

    def on_truth(self, msg) -> None:
        self.truth.append((msgs.stamp_seconds(msg.header.stamp), msg))

    def on_tactile(self, msg) -> None:
        pressure = np.asarray(msg.pressure, np.float32).reshape(msg.rows, msg.cols)
        self.tactile[msg.hand] = (msgs.stamp_seconds(msg.header.stamp), self.layout.region_means(pressure))
        self.pressure[msg.hand] = (msgs.stamp_seconds(msg.header.stamp), pressure)

    # --- simulated detector: projected truth ------------------------------------------------
    def on_frame(self, msg) -> None:
        stamp = msgs.stamp_seconds(msg.header.stamp)
        if not self.truth or len(self.cameras) < 2:
            return
        _, truth = min(self.truth, key=lambda st: abs(st[0] - stamp))
        hand_names, object_names = list(truth.hand_names), list(truth.object_names)
        if self.recon is None or self.recon.hand_names != hand_names or self.recon.object_names != object_names:
            self.recon = Reconstructor(self.params.task, tuple(hand_names), self.params.gate_px,
                                       fit_hands=self.params.fit_hands, object_names=object_names)
        points = np.concatenate([np.asarray(truth.hand_keypoints, float).reshape(-1, 3),
                                 np.asarray(truth.object_keypoints, float).reshape(-1, 3)])
        visible = np.concatenate([np.asarray(truth.hand_visible), np.asarray(truth.object_visible)]) \
            if len(truth.hand_visible) else None
        names = sorted(self.cameras)
        t0 = time.perf_counter()
        uv, seen = self.simulated.detect([self.cameras[c] for c in names], points, visible)
        detect_s = time.perf_counter() - t0
        self._reconstruct(stamp, names, uv, seen.astype(float), {"detect": detect_s})

    # --- learned detector: images -----------------------------------------------------------
    def on_image(self, msg, key: str) -> None:
        self._add(msgs.stamp_seconds(msg.header.stamp), key.split("/")[2], bytes(msg.data))

    def announced_cameras(self) -> set[str]:
        """Cameras whose CameraInfo publisher is live (its type token), known before their first message."""
        return {key.split("/")[2] for sub in self.info_subs for key in list(sub.publishers)}

    def _add(self, stamp: float, item: str, payload: object) -> None:
        # Until a first frame set is out, the cameras announced count too: a restarted recon's first
        # set is not released with the one camera whose CameraInfo came first (then lost: too few views).
        cameras = set(self.cameras) | (self.announced_cameras() if not self.buffer.released else set())
        expected = cameras | {info_key(c) for c in cameras}
        released = self.buffer.add(stamp, item, payload, expected)
        if not released:
            return
        scheduled = bool(self.ready)
        self.ready.extend(released)
        while len(self.ready) > WAITING_SETS:
            self.ready.popleft()
            self.frame_sets_behind += 1
        if not scheduled:  # after the samples already queued on the loop are in
            self.node.loop.call_soon(self._detect_ready)

    def _detect_ready(self) -> None:
        """Detects the oldest released frame set still waiting (at most ``WAITING_SETS`` wait: they
        are whole sets, so no queue drops an image apart from its CameraInfo), then the next one
        after the samples queued meanwhile."""
        stamp, items = self.ready.popleft()
        try:
            self._detect_images(stamp, items)
        except Exception as exc:  # as a handler's: counted and logged, the next frame set goes on
            self.node.handler_failed(self.images_key, exc)
        if self.ready:
            self.node.loop.call_soon(self._detect_ready)

    def _detect_images(self, stamp: float, items: dict[str, object]) -> None:
        t0 = time.perf_counter()
        views = []
        for camera in sorted(k for k in items if not k.endswith(INFO_SUFFIX)):
            model = items.get(info_key(camera))
            if model is None:  # its CameraInfo of this stamp never came: its window is unknown
                self.node.stats.count("image_without_info", camera)
                continue
            rgb = decode_window(items[camera], model)
            if rgb is None:
                self.node.stats.count("corrupt_jpeg", camera)
                continue
            views.append(View(camera, model, rgb))
        t1 = time.perf_counter()
        if len(views) < 2:
            self.node.stats.count("too_few_cameras")
            return
        uv, confidence = self.learned.detect(views)
        t2 = time.perf_counter()
        if uv.shape != (len(views), self.recon.n_points, 2) or confidence.shape != uv.shape[:2]:
            self.node.stats.count("detector_shape")
            self.node.set_status("error", f"detector returned {uv.shape}, expected "
                                          f"({len(views)}, {self.recon.n_points}, 2) for task {self.params.task}")
            return
        stages = {f"detect_{k}": v for k, v in getattr(self.learned, "times", {}).items()}  # the detector's own stages
        self._reconstruct(stamp, [v.camera for v in views], uv, confidence,
                          {"decode": t1 - t0, "detect": t2 - t1, **stages})

    # --- the 3-D stages and the scene ---------------------------------------------------------
    def _reconstruct(self, stamp: float, cameras: list[str], uv: np.ndarray, confidence: np.ndarray,
                     times: dict) -> None:
        P = np.stack([self.cameras[c].P for c in cameras])
        models = [self.cameras[c] for c in cameras]
        windows = np.array([m.roi or (0, 0, m.width, m.height) for m in models], float)
        r: Reconstruction = self.recon.step(P, uv, confidence, windows)
        self.times.append({**times, **r.times})
        self.frame_sets += 1
        self.scene_pub.put(self._scene(stamp, r))
        self._tactile_mesh(stamp, r)

    def _scene(self, stamp: float, r: Reconstruction) -> object:
        hand_names = self.recon.hand_names
        fresh = {h: v for h, (t, v) in self.tactile.items() if abs(stamp - t) < TACTILE_MAX_AGE_S}
        tactile, tactile_mask = tactile_matrix(hand_names, fresh)
        return scene_message(stamp, hand_names, r.hands, r.hand_mask, self.recon.object_names, r.objects,
                             r.object_mask, tactile, tactile_mask)

    def _tactile_mesh(self, stamp: float, r: Reconstruction) -> None:
        if self.projector is None:  # the cell map was refused
            return
        t0 = time.perf_counter()
        fresh = {h: p for h, (t, p) in self.pressure.items() if abs(stamp - t) < TACTILE_MAX_AGE_S}
        msg, skipped = self.projector.message(stamp, self.recon.hand_names, r.hands, r.hand_mask, fresh)
        self.times[-1]["tactile_mesh"] = time.perf_counter() - t0  # a stage of @health's stage_ms_median
        for hand, why in skipped.items():  # keypoints missing, or a bad glove frame
            self.node.stats.count(f"tactile_mesh_{why}", hand)
        self.mesh_pub.put(msg)

