"""aniposelib's triangulation of the recon bench's 2-D detections; runs in the bench's aniposelib venv
(bench/calibration.py makes it), so only numpy and aniposelib are imported here.

``python triangulate_sessions.py IN.npz OUT.npz``: IN holds the cameras (K, rvec, tvec, image
size), per session the detections ``uv_<s>`` (C,T,J,2, NaN where the detector gave nothing above
its threshold), their confidences ``score_<s>`` (C,T,J) and the hand skeleton's bones
(``bones``, pairs of joint indices of the J points). OUT gets per session
``ransac_<s>`` (T,J,3): ``CameraGroup.triangulate_ransac`` (every subset of the views, the one
with the lowest reprojection error), and ``optim_<s>`` (T,J,3): ``triangulate_optim`` (RANSAC
initialisation, then one least-squares problem over the session with temporal smoothing and
constant bone lengths, soft-L1 reprojection loss), with the seconds each took.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from aniposelib.cameras import Camera, CameraGroup


def main(src: str, dst: str) -> None:
    data = np.load(src)
    cams = [Camera(matrix=K, dist=np.zeros(5), size=tuple(int(v) for v in size), rvec=rvec, tvec=tvec,
                   name=f"cam{i}")
            for i, (K, rvec, tvec, size) in enumerate(zip(data["K"], data["rvec"], data["tvec"], data["size"],
                                                          strict=True))]
    group = CameraGroup(cams)
    bones = data["bones"].astype(int).tolist()
    out = {}
    for s in range(int(data["sessions"])):
        uv, score = data[f"uv_{s}"], data[f"score_{s}"]
        C, T, J, _ = uv.shape
        t0 = time.perf_counter()
        p3d, _, picked_2d, _ = group.triangulate_ransac(uv.reshape(C, T * J, 2), min_cams=2)
        out[f"ransac_{s}"] = p3d.reshape(T, J, 3)
        t1 = time.perf_counter()
        # triangulate_optim(init_ransac=True) without its second RANSAC pass: the same initialisation
        out[f"optim_{s}"] = group.optim_points(picked_2d.reshape(C, T, J, 2), p3d.reshape(T, J, 3),
                                               constraints=bones, scores=score, verbose=False)
        t2 = time.perf_counter()
        out[f"seconds_{s}"] = np.array([t1 - t0, t2 - t1])
    np.savez(dst, **out)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
