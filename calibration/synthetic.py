"""Synthetic detections: board corners projected into known cameras with pixel noise (no rendering).

For tests and benches of the solver on its own: the truth is exact, so recovery can be checked.
"""

from __future__ import annotations

import cv2
import numpy as np

from calibration.detect import Detections, add_view
from shared.charuco import BoardSpec


def project_views(board: BoardSpec, names: list[str], sizes: list[tuple[int, int]], K: list[np.ndarray],
                  dist: list[np.ndarray], world_T_cam: list[np.ndarray], world_T_board: list[np.ndarray],
                  noise_px: float = 0.1, seed: int = 0) -> Detections:
    """Detections of the corners in front of each camera and inside its image, kept or skipped as detected."""
    rng = np.random.default_rng(seed)
    obj = board.corners()
    det = Detections(list(names), list(sizes), len(world_T_board))
    for f, wTb in enumerate(world_T_board):
        for c in range(len(names)):
            cTb = np.linalg.inv(world_T_cam[c]) @ wTb
            p = obj @ cTb[:3, :3].T + cTb[:3, 3]
            front = p[:, 2] > 0.05
            # the printed side faces -z of the board: seen only when the camera is on that side
            facing = (cTb[:3, :3] @ np.array([0, 0, -1.0])) @ -cTb[:3, 3] > 0
            uv = cv2.projectPoints(obj, cv2.Rodrigues(cTb[:3, :3])[0], cTb[:3, 3], K[c], dist[c])[0].reshape(-1, 2)
            w, h = sizes[c]
            inside = front & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
            ids = np.flatnonzero(inside) if facing else np.zeros(0, int)
            found = (ids, uv[ids] + rng.normal(0, noise_px, (len(ids), 2))) if len(ids) else None
            add_view(det, c, f, found, board)
    return det
