"""aniposelib's calibration of the bench's detections; runs in the bench's own venv (aniposelib needs
opencv-contrib-python, a second cv2 wheel that must not share the project's venv).

``python calibrate_rows.py IN.json OUT.json``: IN holds the board, camera names and image sizes,
and per camera the detected ChArUco corners (frame set, ids, pixels); OUT gets each camera's
intrinsics and pose (aniposelib's convention: rvec/tvec map its rig frame to the camera), the
registration frame set's corners triangulated in its rig frame, and the solver's time.
Only numpy and aniposelib are imported here.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
from aniposelib.boards import CharucoBoard
from aniposelib.cameras import CameraGroup


def main(src: str, dst: str) -> None:
    data = json.loads(open(src).read())
    b = data["board"]
    bits, size = int(b["dictionary"][5]), int(b["dictionary"].split("_")[-1])  # "DICT_4X4_50" -> 4, 50
    board = CharucoBoard(b["squares_x"], b["squares_y"], b["square_m"], b["marker_m"], marker_bits=bits,
                         dict_size=size)
    group = CameraGroup.from_names(data["names"])
    for cam, (w, h) in zip(group.cameras, data["image_sizes"], strict=True):
        cam.set_size((w, h))
    rows = [[{"framenum": (0, v["frame"]), "ids": np.array(v["ids"], int).reshape(-1, 1),
              "corners": np.array(v["corners"], np.float64).reshape(-1, 1, 2)} for v in views]
            for views in data["views"]]
    t0 = time.perf_counter()
    error = group.calibrate_rows(rows, board, init_intrinsics=True, init_extrinsics=True, verbose=False)
    seconds = time.perf_counter() - t0
    # the registration frame set's corners, triangulated in aniposelib's rig frame
    reg = data["registration_frame"]
    n_ids = (b["squares_x"] - 1) * (b["squares_y"] - 1)
    p2d = np.full((len(data["names"]), n_ids, 2), np.nan)
    for c, views in enumerate(data["views"]):
        for v in views:
            if v["frame"] == reg:
                p2d[c, v["ids"]] = v["corners"]
    seen = np.sum(~np.isnan(p2d[:, :, 0]), axis=0) >= 2
    p3d = group.triangulate(p2d[:, seen])
    out = {"seconds": seconds, "error": float(error), "cameras": group.get_dicts(),
           "registration_ids": np.flatnonzero(seen).tolist(), "registration_points": np.asarray(p3d).tolist()}
    with open(dst, "w") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
