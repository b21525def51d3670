"""Which hand each 2-D hand detection belongs to, decided in 3-D from the hands recon tracks (pure).

A keypoint network that sees both hands in one window sometimes puts the left and the right
channel of a keypoint on the same hand, or swaps them. Triangulation cannot repair that: a swap
seen by several views is a consistent wrong point. Before triangulating, each view's detection of
keypoint k (from either hand's channel) is given to the tracked hand whose last keypoints lie
nearest its viewing ray; two detections claiming one hand keep the nearer, and a detection far from
every tracked hand is dropped. A hand with no track keeps the detections its own channel reports
that are not near a tracked hand, so a lost hand is found again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.geometry import cross

GATE_M = 0.08  # a detection whose ray passes farther than this from every keypoint of its hand is not that hand's


@dataclass
class Assignment:
    confidence: np.ndarray  # (C, N) the input's, zero where a detection was dropped
    uv: np.ndarray  # (C, N, 2) detections moved to the hand they belong to
    swapped: int  # detections moved to the other hand's channel
    dropped: int  # detections dropped (a second claim on one hand, or near no tracked hand)


def ray_distances(P: np.ndarray, uv: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distances (C, K, M) from each view's ray through uv (C, K, 2) to the 3-D points (M, 3)."""
    M, p4 = P[:, :, :3], P[:, :, 3]
    centre = -np.linalg.solve(M, p4[..., None])[..., 0]  # (C, 3)
    homog = np.concatenate([uv, np.ones(uv.shape[:-1] + (1,))], axis=-1)  # (C, K, 3)
    d = np.linalg.solve(M[:, None], homog[..., None])[..., 0]
    d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
    rel = points[None, None, :, :] - centre[:, None, None, :]  # (C, 1, M, 3)
    return np.linalg.norm(cross(rel, d[:, :, None, :]), axis=-1)


def absent_hands(confidence: np.ndarray, hands: int, keypoints: int, min_median: float) -> np.ndarray:
    """(C, H) bool: views whose detections of a hand are too weak, as a whole, to show that hand (a
    window the hand has left: the network's channels then peak weakly on whatever looks most like
    it, often consistently across views)."""
    conf = np.nan_to_num(np.asarray(confidence, float))[:, :hands * keypoints].reshape(len(confidence), hands,
                                                                                         keypoints)
    return np.median(conf, axis=-1) < min_median


def assign_hands(P: np.ndarray, uv: np.ndarray, confidence: np.ndarray, tracked: list[np.ndarray | None],
                 keypoints: int, threshold: float, gate_m: float = GATE_M) -> Assignment:
    """Reassigns the hand channels of (C, N) detections; channels 0..H*keypoints-1 are the hands'
    in ``tracked``'s order, the rest pass through. ``tracked[h]``: hand h's last keypoints (K, 3)
    that were observed, or None when it is not tracked. Detections with confidence below
    ``threshold`` count as none."""
    uv = np.array(uv, float, copy=True)
    conf = np.array(confidence, float, copy=True)
    H = len(tracked)
    known = [h for h in range(H) if tracked[h] is not None and len(tracked[h])]
    if not known or len(P) == 0:
        return Assignment(conf, uv, 0, 0)
    C = len(P)
    hand_uv = uv[:, :H * keypoints].reshape(C, H, keypoints, 2)
    hand_conf = conf[:, :H * keypoints].reshape(C, H, keypoints)
    # dist[c, h_from, k, h_to]: ray of hand h_from's detection of k to hand h_to's nearest keypoint
    dist = np.full((C, H, keypoints, H), np.inf)
    flat_uv = np.nan_to_num(hand_uv.reshape(C, H * keypoints, 2))
    for h in known:
        dist[..., h] = ray_distances(P, flat_uv, np.asarray(tracked[h], float)).min(axis=-1).reshape(C, H, keypoints)
    present = hand_conf >= threshold
    own = dist[:, np.arange(H), :, np.arange(H)].transpose(1, 0, 2)  # (C, H, K): to the channel's own hand
    own_untracked = np.array([h not in known for h in range(H)])[None, :, None]
    others = np.where(np.eye(H, dtype=bool)[None, :, None, :], np.inf, dist)  # the other hands only
    target = np.argmin(others, axis=-1)
    near_other = np.take_along_axis(others, target[..., None], axis=-1)[..., 0] <= gate_m
    # A detection stays with its own channel's hand when its ray passes near that hand, or, for a
    # hand without a track, when it passes near no tracked hand.
    stays = present & np.where(own_untracked, ~near_other, own <= gate_m)
    moves = present & ~stays & near_other
    new_uv = np.where(stays[..., None], hand_uv, 0.0)
    new_conf = np.where(stays, hand_conf, 0.0)
    swapped = 0
    for h_from in range(H):
        for h_to in range(H):
            # A moved detection fills another hand's keypoint only where that hand has none of its own.
            take = moves[:, h_from] & (target[:, h_from] == h_to) & ~stays[:, h_to]
            new_uv[:, h_to][take] = hand_uv[:, h_from][take]
            new_conf[:, h_to][take] = hand_conf[:, h_from][take]
            swapped += int(take.sum())
    kept = int(stays.sum()) + swapped
    uv[:, :H * keypoints] = new_uv.reshape(C, H * keypoints, 2)
    conf[:, :H * keypoints] = new_conf.reshape(C, H * keypoints)
    return Assignment(conf, uv, swapped, int(present.sum()) - kept)


def gate_tracked(P: np.ndarray, uv: np.ndarray, confidence: np.ndarray, tracked: np.ndarray, known: np.ndarray,
                 gate_m: float = GATE_M) -> tuple[np.ndarray, int]:
    """Drops detections (C, K) of points tracked at ``tracked`` (K, 3) (where ``known``) whose rays pass
    farther than ``gate_m`` from the tracked point: a point moves less than that between frame sets.
    Returns the confidence and how many detections were dropped."""
    conf = np.array(confidence, float, copy=True)
    idx = np.flatnonzero(known)
    if not len(idx) or len(P) == 0:
        return conf, 0
    d = ray_distances(P, np.nan_to_num(uv[:, idx]), np.asarray(tracked, float)[idx])  # (C, k, k)
    far = (np.diagonal(d, axis1=1, axis2=2) > gate_m) & (conf[:, idx] > 0)
    conf[:, idx] = np.where(far, 0.0, conf[:, idx])
    return conf, int(far.sum())


def outside_windows(P: np.ndarray, points: np.ndarray, known: np.ndarray, windows: np.ndarray,
                    margin_px: float = 2.0) -> np.ndarray:
    """(C, K) bool: tracked points (K, 3) (where ``known``) that project outside a view's readout
    window (C, 4: x, y, width, height in full-image pixels) or behind it: that view cannot have seen
    them, whatever its network reports there."""
    out = np.zeros((len(P), len(points)), bool)
    idx = np.flatnonzero(known)
    if not len(idx) or len(P) == 0:
        return out
    X = np.c_[np.asarray(points, float)[idx], np.ones(len(idx))]
    proj = np.einsum("cij,nj->cni", P, X)
    z = proj[..., 2]
    uv = proj[..., :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[..., None]
    w = np.asarray(windows, float)[:, None, :]
    inside = (uv[..., 0] >= w[..., 0] - margin_px) & (uv[..., 0] <= w[..., 0] + w[..., 2] - 1 + margin_px) & \
        (uv[..., 1] >= w[..., 1] - margin_px) & (uv[..., 1] <= w[..., 1] + w[..., 3] - 1 + margin_px) & (z > 0)
    out[:, idx] = ~inside
    return out
