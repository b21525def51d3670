"""LEARNED 2-D keypoint detector (thesis 5.6): a U-Net predicts one heatmap per keypoint in each
camera's readout window; a sub-pixel peak per heatmap gives the keypoint's pixel and confidence.

The network sees only images. Each view's window image (CameraInfo.roi) is letterboxed into the
network's fixed input (scaled to fit, padded bottom/right), the peaks are mapped back through the
letterbox and the window offset to full-image pixels, so recon triangulates with the full-image
projection matrices. A second stage, when trained (hands.json beside the graph), crops each hand
around its centre triangulated from the first stage's peaks and re-detects its 21 keypoints there
(services/recon/hand_crops.py); an object stage, when trained (objects.json), does the same per
object at the window's own resolution (services/recon/object_crops.py). Weights come from ``xm
detector train``, ``xm detector train-hands`` and ``xm detector train-objects`` (perception/);
inference runs through
ONNX Runtime when the trained graph was exported (the fastest CPU runtime measured by
bench/detector.py), otherwise through torch. The default weights are the ones shipped in
models/detector/ (the ONNX graph and its meta.json).
"""

from __future__ import annotations

import functools
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn

from services.recon import hand_crops, object_crops
from services.recon.detector import HAND_PRESENT_CONFIDENCE, CameraModel
from services.recon.onnx_graphs import WeightsMissingError, check_precision, has_onnxruntime, onnx_runner
from services.recon.triangulation import triangulate_robust

# The shipped network (in git: model.onnx + meta.json, `make detector` regenerates it); training
# writes its outputs (weights.pt, loss.png, the labelled sets) under TRAINING_DIR, outside git.
DEFAULT_WEIGHTS_DIR = Path(__file__).resolve().parents[2] / "models" / "detector"
TRAINING_DIR = Path("runs/detector")
INPUT_SIZE = (64, 48)  # network input (width, height): fits the P6 budget on 2 cores (bench/detector.py)
HAND_INPUT = 32  # the second stage's square input per hand crop (services/recon/hand_crops.py)
OBJECT_INPUT = 32  # the object stage's square input per object crop (services/recon/object_crops.py)
TRAIN_HINT = "regenerate them with `make detector` (xm detector label && xm detector train)"


def _conv(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.ReLU(inplace=True))


class UNet(nn.Module):
    """Twelve 3x3 convolutions, 32 -> 64 -> 128 -> 256 channels and back to 32, ReLU, max pooling,
    skip connections by concatenation, then a 1x1 convolution to one heatmap per keypoint at the
    input's resolution. Input height and width must be multiples of 8 (three poolings)."""

    def __init__(self, keypoints: int) -> None:
        super().__init__()
        self.keypoints = keypoints
        self.enc0 = nn.Sequential(_conv(3, 32), _conv(32, 32))
        self.enc1 = nn.Sequential(_conv(32, 64), _conv(64, 64))
        self.enc2 = nn.Sequential(_conv(64, 128), _conv(128, 128))
        self.bottom = nn.Sequential(_conv(128, 256), _conv(256, 256))
        self.dec2 = _conv(256 + 128, 128)
        self.dec1 = _conv(128 + 64, 64)
        self.dec0 = nn.Sequential(_conv(64 + 32, 32), _conv(32, 32))
        self.head = nn.Conv2d(32, keypoints, 1)
        self.pool = nn.MaxPool2d(2)
        self.up = nn.Upsample(scale_factor=2, mode="nearest")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e0 = self.enc0(x)
        e1 = self.enc1(self.pool(e0))
        e2 = self.enc2(self.pool(e1))
        b = self.bottom(self.pool(e2))
        d2 = self.dec2(torch.cat([self.up(b), e2], 1))
        d1 = self.dec1(torch.cat([self.up(d2), e1], 1))
        d0 = self.dec0(torch.cat([self.up(d1), e0], 1))
        return self.head(d0)


def to_input(images: list[np.ndarray], size: tuple[int, int] = INPUT_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """Letterboxes RGB uint8 images (H, W, 3) into a float batch (B, 3, h, w) in [0, 1]; returns it
    and each image's scale (network pixels per image pixel)."""
    w, h = size
    batch = np.zeros((len(images), 3, h, w), np.float32)
    scales = np.zeros(len(images))
    for i, img in enumerate(images):
        s = min(w / img.shape[1], h / img.shape[0])
        nw, nh = max(1, round(img.shape[1] * s)), max(1, round(img.shape[0] * s))
        small = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
        batch[i, :, :nh, :nw] = small.transpose(2, 0, 1) / 255.0
        scales[i] = s
    return batch, scales


def image_to_net(uv: np.ndarray, scale: float) -> np.ndarray:
    """Window pixel -> network pixel (pixel centres at integers on both sides)."""
    return (np.asarray(uv, float) + 0.5) * scale - 0.5


def net_to_full(uv: np.ndarray, scale: float, roi: tuple[int, int, int, int] | None) -> np.ndarray:
    """Network pixel -> full-image pixel: undo the letterbox, then add the window's offset."""
    x0, y0 = (roi[0], roi[1]) if roi else (0, 0)
    return (np.asarray(uv, float) + 0.5) / scale - 0.5 + np.array([x0, y0], float)


def peaks(heatmaps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel peak of each heatmap (..., H, W): the maximum pixel, refined per axis by the
    parabola through the logarithms of it and its two neighbours (exact for a Gaussian peak, the
    training target's shape). Returns uv (..., 2) in heatmap pixels and the fitted peak's height
    (...) as the confidence."""
    hm = np.asarray(heatmaps, np.float32)
    lead, (H, W) = hm.shape[:-2], hm.shape[-2:]
    flat = hm.reshape(-1, H, W)
    n = np.arange(len(flat))
    py, px = np.divmod(flat.reshape(len(flat), -1).argmax(axis=1), W)
    conf = flat[n, py, px]
    uv = np.stack([px, py], -1).astype(float)
    log_peak = np.zeros(len(flat))  # the fitted peak's height over the maximum pixel's, in logs
    for axis, (pos, size) in enumerate(((px, W), (py, H))):
        inner = (pos > 0) & (pos < size - 1)
        lo, hi = np.clip(pos - 1, 0, size - 1), np.clip(pos + 1, 0, size - 1)
        if axis == 0:
            a, b = flat[n, py, lo], flat[n, py, hi]
        else:
            a, b = flat[n, lo, px], flat[n, hi, px]
        floor = np.maximum(conf, 1e-12) * 1e-6  # keeps the logs finite where a neighbour is ~0
        la, lc, lb = (np.log(np.maximum(v, floor)) for v in (a, conf, b))
        curv = la - 2 * lc + lb
        step = np.where(curv < -1e-9, 0.5 * (la - lb) / np.where(curv < -1e-9, curv, -1.0), 0.0)
        step = np.where(inner & (conf > 0), np.clip(step, -0.5, 0.5), 0.0)
        uv[:, axis] += step
        log_peak += np.maximum(0.5 * (lb - la) * step + 0.5 * curv * step**2, 0.0)
    return uv.reshape(*lead, 2), (conf * np.exp(log_peak)).reshape(lead)


@dataclass
class View:
    """One camera's frame as recon holds it: the name, the camera model (full-image P, size, window)
    and the decoded RGB window image (H, W, 3) uint8 whose size equals the window's."""
    camera: str
    model: CameraModel
    image: np.ndarray


def load_meta(folder: Path) -> dict:
    path = Path(folder) / "meta.json"
    if not path.exists():
        raise WeightsMissingError(f"no detector weights in {folder} (meta.json missing); {TRAIN_HINT}")
    return json.loads(path.read_text())


class LearnedDetector:
    """Loads the trained network from ``folder`` (meta.json, weights.pt, optional model.onnx) and
    detects every keypoint in every view: ``detect(views) -> (uv (C, N, 2), confidence (C, N))`` in
    full-image pixels, N = len(self.names)."""

    def __init__(self, folder: str | Path = DEFAULT_WEIGHTS_DIR, runtime: str = "auto", threads: int = 2,
                 precision: str = "auto", object_views: int = object_crops.VIEWS, object_reuse: bool = True,
                 object_present_confidence: float | None = None,
                 object_verify_shift: float = object_crops.VERIFY_SHIFT,
                 object_busy_m: float = object_crops.BUSY_M) -> None:
        """``precision`` (ONNX Runtime only): "auto" runs each stage's int8 graph (``xm detector
        quantize``) when it was made from that stage's float graph, else the float one; "int8"
        requires it; "float32" never uses it. ``object_views``: views the object stage crops per
        object (its best; 0: every view);
        ``object_reuse``: a resting object's detections stand in for its crops on every other frame
        set (object_crops.ObjectSchedule; False: every object is cropped on every frame set);
        ``object_present_confidence``: a crop whose peaks of its object have a lower mean
        confidence is dropped (default: ``present_confidence`` in objects.json, else
        ``object_crops.PRESENT_CONFIDENCE``; 0: off); ``object_verify_shift``: a kept crop under
        ``object_crops.TRUSTED`` is checked by a twin shifted this many half sides (0: off);
        ``object_busy_m``: an object a hand's centre is this near is never reused (0: off)."""
        folder = Path(folder)
        self.meta = load_meta(folder)
        self.names: list[str] = list(self.meta["keypoints"])
        self.size = tuple(self.meta["input_size"])
        self.sigma = float(self.meta.get("sigma", 1.5))
        self.hand_present_confidence = float(self.meta.get("hand_present_confidence", HAND_PRESENT_CONFIDENCE))
        if runtime == "auto":
            runtime = "onnx" if (folder / "model.onnx").exists() and has_onnxruntime() else "torch"
        check_precision(precision)  # here too: the torch runtime never reaches onnx_runner
        self.runtime = runtime
        self.precision: dict[str, str] = {}  # per graph stem: the precision it runs at, and why when not int8

        def network(stem: str, weights: str, keypoints: int):
            run, self.precision[stem] = _network(folder / f"{stem}.onnx", folder / weights, keypoints, runtime,
                                                 threads, precision)
            return run

        self._run = network("model", "weights.pt", len(self.names))
        # The second stage (one hand per crop), when trained: hands.json beside its graph or weights.
        self.hand_meta = json.loads((folder / "hands.json").read_text()) if (folder / "hands.json").exists() else None
        self._run_hand = None
        if self.hand_meta is not None:
            self._run_hand = network("hands", "hands.pt", hand_crops.KEYPOINTS)
            self.hand_size = int(self.hand_meta["input_size"])
        self.hand_slices = [slice(i, i + hand_crops.KEYPOINTS) for i in range(0, 2 * hand_crops.KEYPOINTS,
                                                                                 hand_crops.KEYPOINTS)]
        # The object stage (one object per crop), when trained: objects.json beside its graph or weights.
        first = 2 * hand_crops.KEYPOINTS
        self.object_meta = json.loads((folder / "objects.json").read_text()) \
            if (folder / "objects.json").exists() else None
        self._run_object = None
        self.object_slices = [sl for _, sl in object_crops.object_slices(self.names, first)]
        if self.object_meta is not None:
            if list(self.object_meta["keypoints"]) != self.names[first:]:
                raise ValueError(f"object stage in {folder}: keypoints {self.object_meta['keypoints']} are not the "
                                 f"first stage's {self.names[first:]}; {TRAIN_HINT}")
            self._run_object = network("objects", "objects.pt", len(self.names) - first)
            self.object_size = int(self.object_meta["input_size"])
            self.object_half_m = float(self.object_meta.get("half_size_m", object_crops.HALF_SIZE_M))
        self.object_present_confidence = float(object_present_confidence if object_present_confidence is not None
                                               else (self.object_meta or {}).get("present_confidence",
                                                                                 object_crops.PRESENT_CONFIDENCE))
        self.object_views = object_views
        self.object_verify_shift, self.object_busy_m = object_verify_shift, object_busy_m
        self.schedule = object_crops.ObjectSchedule(len(self.object_slices), reuse=object_reuse)
        self.object_crops = 0  # crops the object stage ran, over all frame sets
        self.object_crops_missed = 0  # of those, dropped as too weak to show their object
        self.object_crops_unsteady = 0  # of those, dropped as their peaks followed a shifted twin crop
        self.times: dict[str, float] = {}  # seconds of the last detect(), per stage

    def reset(self) -> None:
        """Forgets the objects' held detections (a new session or recording)."""
        self.schedule.reset()

    def heatmaps(self, batch: np.ndarray) -> np.ndarray:
        return self._run(batch)

    def hand_heatmaps(self, crops: np.ndarray) -> np.ndarray | None:
        """The hand stage's heatmaps of hand crops (B,3,s,s); None without a hand stage."""
        return None if self._run_hand is None else self._run_hand(crops)

    def detect(self, views: list[View]) -> tuple[np.ndarray, np.ndarray]:
        images = []
        for v in views:
            img = np.asarray(v.image)
            x0, y0, w, h = v.model.roi or (0, 0, v.model.width, v.model.height)
            if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
                raise ValueError(f"camera {v.camera}: expected an RGB uint8 image (H, W, 3), got {img.dtype} "
                                 f"{img.shape}")
            if img.shape[:2] != (h, w):
                raise ValueError(f"camera {v.camera}: image is {img.shape[1]}x{img.shape[0]} but its window "
                                 f"(roi) is {w}x{h}")
            images.append(img)
        if not images:
            return np.zeros((0, len(self.names), 2)), np.zeros((0, len(self.names)))
        t0 = time.perf_counter()
        batch, scales = to_input(images, self.size)
        uv_net, conf = peaks(self.heatmaps(batch))
        uv = np.stack([net_to_full(uv_net[i], scales[i], v.model.roi) for i, v in enumerate(views)])
        conf = np.clip(conf, 0.0, 1.0)
        t1 = time.perf_counter()
        self.times = {"first_stage": t1 - t0}
        geometry = _geometry(views) if self._run_hand is not None or self._run_object is not None else None
        if geometry is not None:  # else no geometry to find hands and objects with: the first stage stands
            first = (uv.copy(), conf.copy())  # both stages start from the first stage's peaks
            hands = None
            if self._run_hand is not None:
                hands = self._refine_hands(views, images, uv, conf, geometry)
            t2 = time.perf_counter()
            self.times["hand_stage"] = t2 - t1
            if self._run_object is not None:
                self._refine_objects(views, images, first, uv, conf, geometry, hands)
                self.times["object_stage"] = time.perf_counter() - t2
        return uv, conf

    def _refine_hands(self, views: list[View], images: list[np.ndarray], uv: np.ndarray, conf: np.ndarray,
                      geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                      ) -> tuple[np.ndarray, np.ndarray] | None:
        """The second stage, in place: every hand found in two views or more is cropped in every
        view around its triangulated centre, and the crop network's 21 peaks replace the first
        stage's for that hand and view (confidence 0 where the crop misses the view's window).
        Returns the hands' centres (H,3) and which were found (H,), or None without geometry."""
        geometry = geometry or _geometry(views)
        if geometry is None:
            return None
        P, calibrated, focal = geometry
        centres, found = hand_crops.hand_centres(P, uv, conf * calibrated[:, None], self.hand_slices)
        centre, half, ok = hand_crops.hand_boxes(P, centres, found, focal)
        ok &= calibrated[:, None]
        size = self.hand_size
        crops, where = [], []
        for c, v in enumerate(views):
            x0, y0, w, h = v.model.roi or (0, 0, v.model.width, v.model.height)
            img = None
            for hand, sl in enumerate(self.hand_slices):
                local = centre[c, hand] - (x0, y0)
                if not ok[c, hand]:
                    continue
                if np.any(local < -half[c, hand]) or np.any(local > np.array([w, h]) + half[c, hand]):
                    conf[c, sl] = 0.0  # the hand's crop shows none of this window: the view does not see it
                    continue
                if img is None:
                    img = images[c].astype(np.float32) / 255.0
                M = hand_crops.crop_matrix(local, half[c, hand], size, mirror=hand == 0)
                crops.append(cv2.warpAffine(img, M, (size, size), flags=cv2.INTER_LINEAR,
                                            borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0)).transpose(2, 0, 1))
                where.append((c, sl, M, (x0, y0)))
        if not crops:
            return centres, found
        uv_crop, conf_crop = peaks(self._run_hand(np.ascontiguousarray(np.stack(crops))))
        for (c, sl, M, offset), u, k in zip(where, uv_crop, conf_crop, strict=True):
            local = hand_crops.to_image(u, M)
            h, w = images[c].shape[:2]
            inside = np.all((local >= -0.5) & (local <= np.array([w, h]) - 0.5), axis=1)
            uv[c, sl] = local + offset
            conf[c, sl] = np.where(inside, np.clip(k, 0.0, 1.0), 0.0)  # a crop reaches past its window: no view
        return centres, found

    def _refine_objects(self, views: list[View], images: list[np.ndarray], first: tuple[np.ndarray, np.ndarray],
                        uv: np.ndarray, conf: np.ndarray,
                        geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                        hands: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """The object stage, in place. Each object found in two views or more (from the first
        stage's peaks, ``first``) is placed at its triangulated centre; the schedule
        (object_crops.ObjectSchedule) says whether to crop it now or reuse its last detections.
        A cropped object is cropped in its ``object_views`` best views at the window's own
        resolution (largest projection, least covered by the ``hands``' centres in front of it),
        all crops in one network call; the crop network's peaks of its keypoints replace the first
        stage's there, and its other views get confidence 0 (the first stage's object peaks are
        mostly on a neighbouring keypoint). A crop too weak to show its object, or whose peaks
        follow a shifted twin of it (``_verify``), gets confidence 0. An object with fewer than two
        usable views keeps the first stage's peaks. An object a hand's centre (``hands``) is
        within ``object_busy_m`` of is cropped on every frame set (it may be moving)."""
        geometry = geometry or _geometry(views)
        if geometry is None:
            return
        P, calibrated, focal = geometry
        uv0, conf0 = first
        centres, found = object_crops.object_centres(P, uv0, conf0 * calibrated[:, None], self.object_slices)
        hand_centres = np.asarray(hands[0])[np.asarray(hands[1], bool)] if hands is not None else np.zeros((0, 3))
        centres, found, busy = self.schedule.track(centres, found, hand_centres)  # BUSY_M even when busy is off
        if self.object_busy_m > 0 and len(hand_centres):
            gap = np.linalg.norm(centres[:, None] - hand_centres[None], axis=-1)
            busy |= gap.min(axis=1) < self.object_busy_m
        refresh, reuse = self.schedule.plan(centres, found, busy)
        cameras = [v.camera for v in views]
        for o in np.flatnonzero(reuse):
            sl = self.object_slices[o]
            held = self.schedule.reuse(o)
            conf[:, sl] = 0.0
            for c, name in enumerate(cameras):
                if name in held:
                    uv[c, sl], conf[c, sl] = held[name]
        if not refresh.any():
            return
        windows = np.array([v.model.roi or (0, 0, v.model.width, v.model.height) for v in views], float)
        known = [self.schedule.keypoints(o, centres[o]) for o in range(len(self.object_slices))]
        hand_centres, hands_found = hands if hands is not None else (None, None)
        scores = object_crops.view_scores(P, focal, windows, centres, refresh, known, hand_centres, hands_found)
        chosen = object_crops.choose_views(scores * calibrated[:, None], self.object_views)
        centre, half, ok = hand_crops.hand_boxes(P, centres, found, focal, half_m=self.object_half_m)
        chosen &= ok
        local = centre - windows[:, None, :2]
        misses = ok & (np.any(local < -half[..., None], axis=-1)
                       | np.any(local > windows[:, None, 2:] + half[..., None], axis=-1))
        for c, o in zip(*np.nonzero(misses & refresh[None, :]), strict=True):
            conf[c, self.object_slices[o]] = 0.0  # its crop shows none of this window: the view does not see it
        jobs = [(c, o, centre[c, o], half[c, o]) for c in range(len(views)) for o in np.flatnonzero(chosen[c])]
        for o in np.flatnonzero(refresh & (chosen.sum(axis=0) < 2)):
            self.schedule.forget(o)  # no crops: the first stage's peaks stand, and it is tried again next time
        if not jobs:
            return
        uv_job, conf_job = self._object_peaks(images, windows, jobs)
        unsteady = self._verify(images, windows, jobs, uv_job, conf_job) if self.object_verify_shift > 0 else set()
        for o in np.flatnonzero(chosen.any(axis=0)):
            conf[:, self.object_slices[o]] = 0.0  # only the cropped views speak for a cropped object
        for j, ((c, o, _, _), u, k) in enumerate(zip(jobs, uv_job, conf_job, strict=True)):
            sl = self.object_slices[o]
            uv[c, sl], conf[c, sl] = u, k
            if j not in unsteady and k.mean() < self.object_present_confidence:
                # the crop missed its object (its centre was off): its peaks lie on whatever it shows
                conf[c, sl] = 0.0
                self.object_crops_missed += 1
        for o in np.flatnonzero(chosen.any(axis=0)):
            sl, views_o = self.object_slices[o], np.flatnonzero(chosen[:, o])
            pts, mask, _ = triangulate_robust(P[views_o], uv[views_o, sl], conf[views_o, sl])
            self.schedule.store(o, centres[o], {cameras[c]: (uv[c, sl].copy(), conf[c, sl].copy()) for c in views_o},
                                pts[mask.astype(bool)] if mask.sum() >= 2 else None)

    def _verify(self, images: list[np.ndarray], windows: np.ndarray, jobs: list[tuple[int, int, np.ndarray, float]],
                uv_job: list[np.ndarray], conf_job: list[np.ndarray]) -> set[int]:
        """In place: each crop kept but not trusted (mean confidence between the present and the
        trusted thresholds) is cropped again shifted diagonally by ``object_verify_shift`` half
        sides, all in one network call; where the two crops' peaks lie more than
        ``object_crops.VERIFY_PX`` apart the crop is dropped (its peaks followed the crop, not the
        object), else its peaks are the two crops' mean. Returns the dropped crops' indices."""
        todo = [j for j, k in enumerate(conf_job) if self.object_present_confidence <= k.mean() < object_crops.TRUSTED]
        dropped: set[int] = set()
        if not todo:
            return dropped
        step = self.object_verify_shift * np.array([1.0, 1.0]) / np.sqrt(2.0)
        uv2, conf2 = self._object_peaks(images, windows, [(c, o, cen + step * h, h)
                                                          for c, o, cen, h in (jobs[j] for j in todo)])
        for j, u, k in zip(todo, uv2, conf2, strict=True):
            if object_crops.disagreement(uv_job[j], conf_job[j], u, k) > object_crops.VERIFY_PX:
                conf_job[j] = np.zeros_like(conf_job[j])
                dropped.add(j)
            else:
                uv_job[j] = 0.5 * (uv_job[j] + u)
        self.object_crops_unsteady += len(dropped)
        return dropped

    def _object_peaks(self, images: list[np.ndarray], windows: np.ndarray,
                      jobs: list[tuple[int, int, np.ndarray, float]]) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The object stage on crops ``jobs`` (view, object, centre in full-image pixels, half side
        in pixels), in one network call: per crop its object's peaks (k,2) in full-image pixels and
        their confidences (k,), 0 where a peak lies outside the view's window."""
        size, base = self.object_size, self.object_slices[0].start
        crops, Ms, scaled = [], [], {}
        for c, _, cen, h in jobs:
            if c not in scaled:
                scaled[c] = images[c].astype(np.float32) / 255.0
            M = hand_crops.crop_matrix(cen - windows[c, :2], h, size, mirror=False)
            crops.append(cv2.warpAffine(scaled[c], M, (size, size), flags=cv2.INTER_LINEAR,
                                        borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0)).transpose(2, 0, 1))
            Ms.append(M)
        self.object_crops += len(crops)
        uv_crop, conf_crop = peaks(self._run_object(np.ascontiguousarray(np.stack(crops))))
        uv_out, conf_out = [], []
        for (c, o, _, _), M, u, k in zip(jobs, Ms, uv_crop, conf_crop, strict=True):
            sl = self.object_slices[o]
            rows = slice(sl.start - base, sl.stop - base)  # the cropped object's channels
            local = hand_crops.to_image(u[rows], M)
            h, w = images[c].shape[:2]
            inside = np.all((local >= -0.5) & (local <= np.array([w, h]) - 0.5), axis=1)
            uv_out.append(local + windows[c, :2])
            conf_out.append(np.where(inside, np.clip(k[rows], 0.0, 1.0), 0.0))
        return uv_out, conf_out


def _geometry(views: list[View]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The views' projection matrices (C,3,4), which are calibrated (C,) and their focal lengths in
    pixels (C,); None with fewer than two calibrated views (no crop can be placed)."""
    if len(views) < 2:
        return None
    P = np.stack([np.asarray(v.model.P, float) for v in views])
    terms = [_camera_terms(p.tobytes()) for p in P]
    calibrated = np.array([ok for ok, _ in terms])
    if calibrated.sum() < 2:
        return None
    return P, calibrated, np.array([f for _, f in terms])


@functools.lru_cache(maxsize=64)
def _camera_terms(P_bytes: bytes) -> tuple[bool, float]:
    """Whether a projection matrix (3x4 float64, as bytes) is calibrated, and its focal length in
    pixels (1.0 when not). Cached: a rig's matrices repeat every frame set, and the rank test and
    decomposition cost about 0.6 ms per view."""
    P = np.frombuffer(P_bytes, float).reshape(3, 4)
    ok = bool(np.linalg.matrix_rank(P[:, :3]) == 3)
    return ok, hand_crops.focal_px(P) if ok else 1.0


def _network(onnx_path: Path, weights: Path, keypoints: int, runtime: str, threads: int,
             precision: str = "auto") -> tuple[Callable[[np.ndarray], np.ndarray], str]:
    """A function batch (B,3,h,w) float32 -> heatmaps (B,K,h,w) through ONNX Runtime or torch, and
    the precision it runs at."""
    if runtime == "onnx":
        return onnx_runner(onnx_path, threads, precision)
    if not weights.exists():
        raise WeightsMissingError(f"no detector weights at {weights}; {TRAIN_HINT}")
    torch.set_flush_denormal(True)  # denormal weights and activations slow CPU convolutions many times
    net = UNet(keypoints)
    net.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True))
    net.eval()

    def run(batch: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return net(torch.from_numpy(batch)).numpy()
    return run, "float32 (torch)"
