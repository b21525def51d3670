"""Initial guesses for the bundle adjustment.

Intrinsics per camera from ``cv2.calibrateCamera`` on its own views; board poses per view from
the same call (or ``solvePnP``); camera extrinsics chained through frame sets that several cameras
saw: relative poses are averaged robustly per camera pair, and each camera is linked to the
reference camera along the maximum spanning tree of the co-visibility graph (edge weight: shared
frame sets), so every link rests on as many shared views as the capture offers.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
from scipy.spatial.transform import Rotation

from calibration.detect import Detection, Detections
from shared.charuco import BoardSpec

MIN_VIEWS = 4  # views a camera needs for its own intrinsics
MIN_SHARED = 3  # frame sets two cameras must share to be linked
MAX_INTRINSIC_VIEWS = 40  # calibrateCamera's cost grows with views; the bundle adjustment uses all


class CaptureUnusableError(RuntimeError):
    """The capture cannot calibrate the rig; the message names the camera(s) and what to do."""


@dataclass
class Initial:
    K: list[np.ndarray]
    dist: list[np.ndarray]
    cam_T_rig: list[np.ndarray]  # (4,4) per camera; the reference camera is the identity
    rig_T_board: dict[int, np.ndarray]  # frame -> (4,4)
    reference: int


def to_T(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float).reshape(3))[0]
    T[:3, 3] = np.asarray(tvec, float).reshape(3)
    return T


def intrinsics(views: list[Detection], board: BoardSpec, size: tuple[int, int], model: str = "full"
               ) -> tuple[np.ndarray, np.ndarray, dict[int, np.ndarray]]:
    """(K, dist, frame -> cam_T_board) of one camera from its views (``model``: see bundle.MODELS)."""
    obj_all = board.corners()
    order = sorted(views, key=lambda v: -len(v.ids))
    step = max(1, len(order) // MAX_INTRINSIC_VIEWS)
    chosen = order[::step][:MAX_INTRINSIC_VIEWS]
    obj = [obj_all[v.ids].astype(np.float32) for v in chosen]
    img = [v.corners.astype(np.float32) for v in chosen]
    flags = cv2.CALIB_FIX_K3  # k3 only in the bundle adjustment, where all views constrain it
    K0 = None
    if model == "centred":
        K0 = cv2.initCameraMatrix2D(obj, img, size)
        K0[0, 2], K0[1, 2] = (size[0] - 1) / 2, (size[1] - 1) / 2  # the image centre, pixel-centre convention
        K0[0, 0] = K0[1, 1] = (K0[0, 0] + K0[1, 1]) / 2
        flags |= (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
                  | cv2.CALIB_ZERO_TANGENT_DIST)
    _, K, dist, _, _ = cv2.calibrateCamera(obj, img, size, K0, None, flags=flags)
    dist = dist.ravel()[:5]
    poses = {}
    for v in views:
        ok, rvec, tvec = cv2.solvePnP(obj_all[v.ids], v.corners, K, dist, flags=cv2.SOLVEPNP_IPPE)
        if ok:
            poses[v.frame] = to_T(rvec, tvec)
    return K, dist, poses


def average_pose(samples: list[np.ndarray]) -> np.ndarray:
    """Robust mean of rigid transforms: the medoid, then the mean of those close to it."""
    rots = Rotation.from_matrix(np.array([T[:3, :3] for T in samples]))
    trans = np.array([T[:3, 3] for T in samples])
    if len(samples) > 2:
        ang = np.array([(rots[i].inv() * rots).magnitude() for i in range(len(samples))])
        dist = np.linalg.norm(trans[:, None] - trans[None], axis=2)
        score = np.median(ang, axis=1) / np.radians(1.0) + np.median(dist, axis=1) / 0.01
        m = int(np.argmin(score))
        keep = (ang[m] < max(3 * np.median(ang[m]), np.radians(0.5))) & (dist[m] < max(3 * np.median(dist[m]), 0.005))
        rots, trans = rots[keep], trans[keep]
    T = np.eye(4)
    T[:3, :3] = rots.mean().as_matrix()
    T[:3, 3] = trans.mean(axis=0)
    return T


def initial_guess(det: Detections, board: BoardSpec, model: str = "full") -> Initial:
    n = len(det.names)
    per_cam = [det.of_camera(c) for c in range(n)]
    never = [det.names[c] for c in range(n) if not per_cam[c]]
    if never:
        raise CaptureUnusableError(
            f"camera(s) {', '.join(never)} never saw the board in {det.n_frames} frame sets: check each is "
            "connected, exposed and focused, then wave the board where it looks (skipped views: "
            + "; ".join(f"{name}: {det.skipped_by_camera()[name]}" for name in never) + ")")
    few = [f"{det.names[c]} ({len(per_cam[c])})" for c in range(n) if len(per_cam[c]) < MIN_VIEWS]
    if few:
        raise CaptureUnusableError(f"camera(s) {', '.join(few)} saw the board in fewer than {MIN_VIEWS} usable views: "
                                "wave the board closer to and across the view of each")
    K, dist, poses = [], [], []
    for c in range(n):
        Kc, dc, pc = intrinsics(per_cam[c], board, det.image_sizes[c], model)
        K.append(Kc)
        dist.append(dc)
        poses.append(pc)
    # co-visibility graph: shared frame sets per camera pair
    frames = [set(p) for p in poses]
    shared = np.array([[len(frames[a] & frames[b]) if a != b else 0 for b in range(n)] for a in range(n)])
    linked = np.where(shared >= MIN_SHARED, shared, 0)
    reference = int(np.argmax(linked.sum(axis=1)))
    # maximum spanning tree = minimum spanning tree on negated weights
    tree = minimum_spanning_tree(-linked.astype(float)).toarray()
    tree = (tree != 0) | (tree.T != 0)
    order, parent = breadth_first_order(tree, reference, directed=False, return_predecessors=True)
    unlinked = sorted(set(range(n)) - set(order.tolist()))
    if unlinked:
        detail = "; ".join(f"{det.names[c]} shares " + (", ".join(
            f"{shared[c, o]} with {det.names[o]}" for o in range(n) if o != c and shared[c, o]) or "none")
            for c in unlinked)
        raise CaptureUnusableError(
            f"camera(s) {', '.join(det.names[c] for c in unlinked)} share fewer than {MIN_SHARED} frame sets with "
            f"the cameras linked to {det.names[reference]} ({detail}): wave the board where these cameras and "
            "their neighbours see it at the same time")
    cam_T_rig = [np.eye(4) for _ in range(n)]
    for c in order[1:]:
        p = parent[c]
        # c_T_p from every frame set both saw: c_T_board @ inv(p_T_board)
        samples = [poses[c][f] @ np.linalg.inv(poses[p][f]) for f in sorted(frames[c] & frames[p])]
        cam_T_rig[c] = average_pose(samples) @ cam_T_rig[p]
    rig_T_board: dict[int, np.ndarray] = {}
    best: dict[int, int] = {}
    for v in det.views:  # each frame set's board pose from the camera that saw most of it
        if v.frame in poses[v.camera] and len(v.ids) > best.get(v.frame, 0):
            best[v.frame] = len(v.ids)
            rig_T_board[v.frame] = np.linalg.inv(cam_T_rig[v.camera]) @ poses[v.camera][v.frame]
    return Initial(K, dist, cam_T_rig, rig_T_board, reference)
