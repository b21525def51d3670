"""The 3-D stages in order, without I/O: triangulate (robust) -> fit (articulated hands, rigid
objects) -> scene arrays with masks. The service and the bench drive it per frame set."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from services.recon.hand_fit import FitConfig, HandTracker
from services.recon.hand_identity import absent_hands, assign_hands, gate_tracked, outside_windows
from services.recon.object_fit import RigidTracker
from services.recon.objects import ObjectSmoother, object_models, pose_objects, task_keypoint_names
from services.recon.triangulation import triangulate_robust
from shared.demo import HAND_NAMES, KEYPOINTS_PER_HAND

SAME_HAND_M = 0.05  # two hands whose keypoints triangulate this close (median) are one hand seen twice
SAME_HAND_MIN_POINTS = 5
# No keypoint of a hand lies farther than this from the median of its keypoints (the simulated
# teacher's fingertips reach 0.118 m; the margin holds larger hands and triangulation noise).
HAND_EXTENT_M = 0.15
CONFIRM_M = 0.02  # a new object track's two first poses agree this well (median keypoint distance)
TRACKED_MIN_POINTS = 5  # reported keypoints of a hand needed to decide other detections' hand by it


def beyond_the_hand(points: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(21,) bool: triangulated keypoints too far from their hand's median keypoint to belong to it
    (a detection that landed on the other hand or elsewhere, agreed on by two or more views)."""
    seen = mask.astype(bool)
    if seen.sum() < SAME_HAND_MIN_POINTS:
        return np.zeros(len(points), bool)
    centre = np.median(points[seen], axis=0)
    return seen & (np.linalg.norm(points - centre, axis=1) > HAND_EXTENT_M)


def one_hand_seen_twice(hands: np.ndarray, mask: np.ndarray, support: np.ndarray) -> int | None:
    """Which of two hands to drop when both triangulated onto the same physical hand (a detector's
    left and right channels both peak on the one hand a window shows): the one whose detections are
    weaker (``support``: mean confidence of its inlier views); None when the hands are apart.

    hands (2,21,3), mask (2,21), support (2,)."""
    both = mask[0].astype(bool) & mask[1].astype(bool)
    if len(hands) != 2 or both.sum() < SAME_HAND_MIN_POINTS:
        return None
    if np.median(np.linalg.norm(hands[0][both] - hands[1][both], axis=1)) >= SAME_HAND_M:
        return None
    return int(np.argmin(support))


@dataclass
class Reconstruction:
    hands: np.ndarray  # (H,21,3), zero where masked
    hand_mask: np.ndarray  # (H,21) uint8
    hand_fitted: np.ndarray  # (H,) bool: the hand model produced the keypoints
    objects: np.ndarray  # (K,3)
    object_mask: np.ndarray  # (K,) uint8
    object_posed: np.ndarray  # (objects,) bool: a rigid fit produced the object's keypoints
    inliers: np.ndarray  # (C,N) views each triangulated point used
    triangulated: np.ndarray  # (N,3) the robust triangulation before the fits, zero where masked
    times: dict = field(default_factory=dict)  # seconds per stage
    # The 2-D detections as the triangulation took them: hand channels reassigned to the hand they
    # belong to (hand_identity.py), dropped or absent ones at confidence 0. ``inliers`` index these.
    uv: np.ndarray | None = None  # (C,N,2)
    confidence: np.ndarray | None = None  # (C,N)


class Reconstructor:
    """Stateful across frame sets through the hand trackers' windows and shapes and the tracked
    objects."""

    def __init__(self, task: str, hand_names: tuple[str, ...] = HAND_NAMES, gate_px: float = 6.0,
                 fit: FitConfig | None = None, fit_hands: bool = True,
                 object_names: list[str] | None = None, identity: bool = True,
                 min_confidence: float = 0.0, hand_present_confidence: float = 0.0,
                 object_fit: str = "kabsch", confirm_objects: bool = True) -> None:
        """``object_names``: the keypoints the detector reports, when they are not the task's own
        (then no rigid model applies and objects stay triangulated points). ``identity``: give hand
        detections to the tracked hand nearest their ray (hand_identity.py); ``min_confidence``:
        detections below it count as none there; ``hand_present_confidence``: a view whose detections of
        a hand have a lower median confidence does not show that hand (a learned detector's
        calibration: ``LearnedDetector.hand_present_confidence``; 0: off). ``object_fit``:
        ``reprojection`` poses each rigid object on its 2-D detections in every view, pooled while
        it rests (object_fit.py); ``kabsch`` on its triangulated keypoints alone (objects.py).
        ``confirm_objects``: a rigid object without a track is reported once two frame sets agree
        on it (``_confirm_new_objects``)."""
        if object_fit not in ("reprojection", "kabsch"):
            raise ValueError(f"object_fit: 'reprojection' or 'kabsch', not {object_fit!r}")
        self.hand_names = list(hand_names)
        names = task_keypoint_names(task)
        self.object_names = names if object_names is None else list(object_names)
        self.models = object_models(task) if self.object_names == names else []
        self.gate_px = gate_px
        self.fit_hands = fit_hands
        self.trackers = {h: HandTracker(h, fit or FitConfig()) for h in self.hand_names}
        self.smoother = ObjectSmoother()
        self.rigid = {m.name: RigidTracker(m.points) for m in self.models} if object_fit == "reprojection" else {}
        self.object_fit_restarts = 0  # a resting object's window restarted: it moved
        self.hands_seen_twice = 0  # frame sets where one hand was dropped as the other's double
        self.beyond_hand = 0  # hand keypoints masked as too far from their hand
        self.identity = identity
        self.min_confidence = min_confidence
        self.hand_present_confidence = hand_present_confidence
        self.hand_views_absent = 0  # (view, hand) pairs whose detections were too weak to show the hand
        self.hand_swaps = 0  # 2-D detections moved to the other hand's channel
        self.hand_detections_dropped = 0  # 2-D hand detections near no tracked hand, or a second claim
        self._tracked: list[np.ndarray | None] = [None] * len(self.hand_names)
        self.object_detections_dropped = 0  # object detections far from where the object is tracked
        self.objects_outside_windows = 0  # object detections in views whose window cannot show the object
        self.confirm_objects = confirm_objects
        self._candidates: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}
        self.objects_unconfirmed = 0  # objects masked on the frame set that would have started their track
        self._objects = np.zeros((len(self.object_names), 3))
        self._objects_known = np.zeros(len(self.object_names), bool)

    def _confirm_new_objects(self, objects: np.ndarray, mask: np.ndarray, posed: np.ndarray) -> None:
        """In place: an object without a track (not reported on the last frame set) is reported
        only when the last frame set put it at the same place (median keypoint distance under
        ``CONFIRM_M``); otherwise it is masked and remembered as a candidate. A new track needs
        two agreeing frame sets: a network's object peaks on whatever a window shows (a hand, after
        a reset moved the objects out of every window) rarely agree twice."""
        for i, m in enumerate(self.models):
            sl = m.slice
            seen = mask[sl].astype(bool)
            last = self._candidates.get(m.name)
            self._candidates[m.name] = (objects[sl].copy(), seen) if seen.any() else None
            if self._objects_known[sl].any() or not seen.any():
                continue  # tracked (the gate holds it), or nothing to report
            both = seen & last[1] if last is not None else np.zeros_like(seen)
            if not both.any() or np.median(np.linalg.norm(objects[sl][both] - last[0][both], axis=1)) >= CONFIRM_M:
                mask[sl], objects[sl], posed[i] = 0, 0.0, False
                self.objects_unconfirmed += 1

    @property
    def n_points(self) -> int:
        return len(self.hand_names) * KEYPOINTS_PER_HAND + len(self.object_names)

    def step(self, P: np.ndarray, uv: np.ndarray, confidence: np.ndarray,
             windows: np.ndarray | None = None) -> Reconstruction:
        """P (C,3,4) of the cameras present; uv (C,N,2) full-image pixels; confidence (C,N);
        ``windows`` (C,4): each view's readout window (x, y, width, height), when known: a tracked
        object outside a view's window is not detected there."""
        t0 = time.perf_counter()
        if self.hand_present_confidence > 0:
            absent = absent_hands(confidence, len(self.hand_names), KEYPOINTS_PER_HAND, self.hand_present_confidence)
            if absent.any():
                self.hand_views_absent += int(absent.sum())
                confidence = np.array(confidence, float, copy=True)
                nh = len(self.hand_names) * KEYPOINTS_PER_HAND
                confidence[:, :nh] *= ~np.repeat(absent, KEYPOINTS_PER_HAND, axis=1)
        if self.identity:
            a = assign_hands(P, uv, confidence, self._tracked, KEYPOINTS_PER_HAND, self.min_confidence)
            uv, confidence = a.uv, a.confidence
            self.hand_swaps += a.swapped
            self.hand_detections_dropped += a.dropped
            nh = len(self.hand_names) * KEYPOINTS_PER_HAND
            obj_conf, dropped = gate_tracked(P, uv[:, nh:], confidence[:, nh:], self._objects, self._objects_known)
            if windows is not None:
                unseen = outside_windows(P, self._objects, self._objects_known, windows) & (obj_conf > 0)
                obj_conf[unseen] = 0.0
                self.objects_outside_windows += int(unseen.sum())
            confidence = np.concatenate([confidence[:, :nh], obj_conf], axis=1)
            self.object_detections_dropped += dropped
        pts, mask, inliers = triangulate_robust(P, uv, confidence, self.gate_px)
        t1 = time.perf_counter()
        H, nh = len(self.hand_names), len(self.hand_names) * KEYPOINTS_PER_HAND
        hands = pts[:nh].reshape(H, KEYPOINTS_PER_HAND, 3).copy()
        hand_mask = mask[:nh].reshape(H, KEYPOINTS_PER_HAND).copy()
        conf = np.nan_to_num(np.asarray(confidence, float))[:, :nh].reshape(-1, H, KEYPOINTS_PER_HAND)
        kept = inliers[:, :nh].reshape(-1, H, KEYPOINTS_PER_HAND)
        support = (conf * kept).sum(axis=(0, 2)) / np.maximum(kept.sum(axis=(0, 2)), 1)
        double = one_hand_seen_twice(hands, hand_mask, support)
        if double is not None:
            self.hands_seen_twice += 1
            sl = slice(double * KEYPOINTS_PER_HAND, (double + 1) * KEYPOINTS_PER_HAND)
            mask[sl], hand_mask[double] = 0, 0
            pts[sl], hands[double] = 0.0, 0.0
            inliers[:, sl] = False
        for i in range(H):
            far = beyond_the_hand(hands[i], hand_mask[i])
            if far.any():
                self.beyond_hand += int(far.sum())
                idx = i * KEYPOINTS_PER_HAND + np.flatnonzero(far)
                mask[idx], hand_mask[i, far] = 0, 0
                pts[idx], hands[i, far] = 0.0, 0.0
                inliers[:, idx] = False
        views = inliers.sum(axis=0).astype(float)
        fitted = np.zeros(H, bool)
        for i, name in enumerate(self.hand_names):
            if not self.fit_hands:
                break
            sl = slice(i * KEYPOINTS_PER_HAND, (i + 1) * KEYPOINTS_PER_HAND)
            hands[i], hand_mask[i], fitted[i] = self.trackers[name].update(pts[sl], mask[sl], views[sl])
        self._tracked = [h[m.astype(bool)] if m.sum() >= TRACKED_MIN_POINTS else None
                         for h, m in zip(hands, hand_mask, strict=True)]
        t2 = time.perf_counter()
        objects, object_mask, posed, rms, used = pose_objects(self.models, pts[nh:], mask[nh:], views[nh:])
        objects = self.smoother.update(self.models, objects, posed, rms, used)
        if self.rigid:
            w = (np.nan_to_num(np.asarray(confidence, float))[:, nh:] > self.min_confidence).astype(float)
            for m in self.models:
                tracker = self.rigid[m.name]
                before = tracker.restarts
                fit = tracker.update(P, uv[:, nh:][:, m.slice], w[:, m.slice], pts[nh:][m.slice], mask[nh:][m.slice])
                self.object_fit_restarts += tracker.restarts - before
                if fit is not None:
                    objects[m.slice], object_mask[m.slice] = fit.points(m.points), 1
                    i = self.models.index(m)
                    posed[i] = True
                    inliers[:, nh + np.arange(m.slice.start, m.slice.stop)] = fit.inliers
        if self.confirm_objects:
            self._confirm_new_objects(objects, object_mask, posed)
        self._objects, self._objects_known = objects.copy(), object_mask.astype(bool)
        t3 = time.perf_counter()
        return Reconstruction(hands, hand_mask, fitted, objects, object_mask, posed, inliers, pts,
                              {"triangulate": t1 - t0, "fit_hands": t2 - t1, "fit_objects": t3 - t2},
                              np.asarray(uv), np.asarray(confidence))
