"""ChArUco corners per camera image, with degenerate views skipped and counted.

``cv2.aruco.CharucoDetector(board).detectBoard`` finds the markers and interpolates the chessboard
corners between them (sub-pixel); ``board.matchImagePoints`` pairs them with board points. A view
is kept only if it can constrain a camera: enough corners spanning two rows and two columns, a
board that covers some of the image, and not seen nearly edge-on (then the corner positions along
the foreshortened axis carry little and the marker decoding is least reliable).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field

import cv2
import numpy as np

from shared.charuco import BoardSpec

MIN_CORNERS = 6
MIN_AREA_FRACTION = 0.002  # hull of the detected corners over the image area
MIN_FORESHORTENING = 0.2  # smallest / largest singular value of the board->image map: ~78 degrees tilt
# Sub-pixel refinement after detectBoard: a half-window of about a seventh of the (foreshortened)
# square side keeps the neighbouring squares' markers out of the window; on rendered 640x480
# frames this halves the camera rotation error against the truth.
SUBPIX_FRACTION = 0.14
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)


@dataclass
class Detection:
    camera: int
    frame: int
    ids: np.ndarray  # (n,) chessboard corner ids
    corners: np.ndarray  # (n,2) pixels, OpenCV convention


@dataclass
class Detections:
    """Every kept view of a capture, plus what was skipped and why."""

    names: list[str]
    image_sizes: list[tuple[int, int]]  # (width, height) per camera
    n_frames: int
    views: list[Detection] = field(default_factory=list)
    skipped: Counter = field(default_factory=Counter)  # (camera index, reason) -> count

    def of_camera(self, cam: int) -> list[Detection]:
        return [v for v in self.views if v.camera == cam]

    def skipped_by_camera(self) -> dict[str, dict[str, int]]:
        out: dict[str, dict[str, int]] = {n: {} for n in self.names}
        for (cam, reason), count in self.skipped.items():
            out[self.names[cam]][reason] = count
        return out


def scale(ids: np.ndarray, corners: np.ndarray, board: BoardSpec) -> np.ndarray | None:
    """Singular values (px per metre, largest first) of the board->image map at the centre of the
    detected corners, or None when no homography fits; their ratio is the foreshortening."""
    obj = board.corners()[ids, :2]
    H, _ = cv2.findHomography(obj, corners, 0)
    if H is None:
        return None
    centre = obj.mean(axis=0)
    x, y, w = H @ np.array([centre[0], centre[1], 1.0])
    J = (H[:2, :2] * w - np.outer([x, y], H[2, :2])) / w**2
    return np.linalg.svd(J, compute_uv=False)


def degenerate(ids: np.ndarray, corners: np.ndarray, board: BoardSpec, image_size: tuple[int, int]) -> str | None:
    """Why a view cannot be used (``too_few``, ``collinear``, ``too_small``, ``edge_on``), or None."""
    if len(ids) < MIN_CORNERS:
        return "too_few"
    cols, rows = ids % (board.squares_x - 1), ids // (board.squares_x - 1)
    if len(np.unique(cols)) < 2 or len(np.unique(rows)) < 2:
        return "collinear"
    hull = cv2.convexHull(corners.astype(np.float32))
    if cv2.contourArea(hull) < MIN_AREA_FRACTION * image_size[0] * image_size[1]:
        return "too_small"
    s = scale(ids, corners, board)
    if s is None:
        return "collinear"
    if s[1] < MIN_FORESHORTENING * s[0]:
        return "edge_on"
    return None


class BoardDetector:
    """One per thread (OpenCV detectors keep state)."""

    def __init__(self, board: BoardSpec) -> None:
        self.spec = board
        self.board = board.board()
        self.detector = cv2.aruco.CharucoDetector(self.board)

    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(ids, corners (n,2)) of the chessboard corners found in an RGB or grey image, or None."""
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        corners, ids, _, _ = self.detector.detectBoard(gray)
        if ids is None or len(ids) == 0:
            return None
        ids, corners = ids.ravel().astype(int), corners.reshape(-1, 2).astype(np.float32)
        s = scale(ids, corners, self.spec) if len(ids) >= 4 else None
        if s is not None:
            half = int(np.clip(SUBPIX_FRACTION * s[1] * self.spec.square_m, 1, 8))
            corners = cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2), (half, half), (-1, -1), SUBPIX_CRITERIA)
        return ids, corners.reshape(-1, 2).astype(float)


class Collector:
    """Detects frame sets as they arrive (``add``), timing the detection alone."""

    def __init__(self, board: BoardSpec) -> None:
        self.board = board
        self.detector = BoardDetector(board)
        self.det: Detections | None = None
        self.seconds = 0.0

    def add(self, index: int, images: list[np.ndarray | None]) -> None:
        t0 = time.perf_counter()
        if self.det is None:
            sizes = [(img.shape[1], img.shape[0]) if img is not None else (0, 0) for img in images]
            self.det = Detections([f"cam{c}" for c in range(len(images))], sizes, 0)
        self.det.n_frames = max(self.det.n_frames, index + 1)
        for c, img in enumerate(images):
            if img is None:
                self.det.skipped[(c, "no_image")] += 1
                continue
            if self.det.image_sizes[c] == (0, 0):
                self.det.image_sizes[c] = (img.shape[1], img.shape[0])
            add_view(self.det, c, index, self.detector.detect(img), self.board)
        self.seconds += time.perf_counter() - t0

    def result(self, names: list[str]) -> Detections:
        if self.det is None:
            raise ValueError("no frame sets were captured")
        if len(names) != len(self.det.names):
            raise ValueError(f"{len(names)} camera names for frame sets of {len(self.det.names)} images")
        self.det.names = list(names)
        return self.det


def add_view(out: Detections, cam: int, frame: int, found: tuple[np.ndarray, np.ndarray] | None,
             board: BoardSpec) -> None:
    """Keep one camera's detection in a frame set, or count why not."""
    if found is None:
        out.skipped[(cam, "not_seen")] += 1
        return
    ids, corners = found
    reason = degenerate(ids, corners, board, out.image_sizes[cam])
    if reason:
        out.skipped[(cam, reason)] += 1
        return
    out.views.append(Detection(cam, frame, ids, corners))
