"""Per-object crops for the detector's object stage (pure).

In a readout window the network's first stage sees the board at about 7 input pixels across and
the camera module at about 3, so its object peaks land on a neighbouring keypoint of the same object
(the board's corners) or a few pixels off, 4 px median in the window (about 2 cm at the rig's
0.9 m). The object stage looks at one object at a time at the window's own resolution, upsampled:
each object's 3-D centre is the median of its confident first-stage peaks per view, triangulated
with a coarse gate (the median of an object's peaks does not move when the first stage exchanges
two of its keypoints), projected back into every view; the crop around it spans a fixed metric
size at that depth. No mirroring: the board's corners are told apart by their handedness.
"""

from __future__ import annotations

import numpy as np

from services.recon.triangulation import triangulate_robust

HALF_SIZE_M = 0.05  # half the crop's side at the object's depth: the board's half diagonal (34 mm) plus slack
MIN_PEAKS = 2  # confident first-stage peaks of an object needed in a view for its centre there
CENTRE_GATE_PX = 12.0  # reprojection gate of the centre's triangulation (the medians are coarse)


def object_slices(names: list[str], first: int) -> list[tuple[str, slice]]:
    """(object, rows) of the keypoints named ``object/point`` from row ``first`` on, in order."""
    out: list[tuple[str, slice]] = []
    for i, n in enumerate(names[first:], start=first):
        obj = n.split("/")[0]
        if out and out[-1][0] == obj:
            out[-1] = (obj, slice(out[-1][1].start, i + 1))
        else:
            out.append((obj, slice(i, i + 1)))
    return out


def object_centres(P: np.ndarray, uv: np.ndarray, conf: np.ndarray, objects: list[slice],
                   threshold: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Each object's 3-D centre from the first stage's peaks: P (C,3,4), uv (C,N,2) full-image
    pixels, conf (C,N). Returns centres (O,3) and a mask (O,) of the objects found in two views or more."""
    C = len(P)
    med = np.zeros((C, len(objects), 2))
    seen = np.zeros((C, len(objects)), bool)
    for o, sl in enumerate(objects):
        for c in range(C):
            ok = conf[c, sl] >= threshold
            if ok.sum() >= min(MIN_PEAKS, sl.stop - sl.start):
                med[c, o] = np.median(uv[c, sl][ok], axis=0)
                seen[c, o] = True
    points, mask, _ = triangulate_robust(P, med, seen.astype(float), gate_px=CENTRE_GATE_PX)
    return points, mask.astype(bool)
