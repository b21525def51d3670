"""The rig calibration file: one JSON file per rig, OpenCV conventions.

Written by ``xm calibrate``, read by camhub (published as CameraInfo) and recon. Pixel coordinates
follow OpenCV (origin at the centre of the top-left pixel); ``K`` and ``dist`` are the
``cv2.calibrateCamera`` intrinsics and distortion (5 coefficients: k1 k2 p1 p2 k3);
``world_T_cam`` maps camera coordinates (x right, y down, z forward) to the world frame in
metres. The world frame is the one the board registration fixes (``board_T_world``).
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

FORMAT = "crossmodal-rig-calibration/1"


class CalibrationError(ValueError):
    """A calibration file is malformed or does not match the rig that reads it."""


@dataclass
class CameraCalibration:
    name: str
    width: int
    height: int
    K: np.ndarray  # (3,3)
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3
    world_T_cam: np.ndarray  # (4,4)
    rms_px: float = float("nan")  # reprojection RMS of the final bundle adjustment

    def projection(self) -> np.ndarray:
        """The (3,4) CameraInfo ``P = K [R | t]`` with [R | t] = cam_T_world."""
        cam_T_world = np.linalg.inv(self.world_T_cam)
        return self.K @ cam_T_world[:3, :]


@dataclass
class RigCalibration:
    cameras: list[CameraCalibration]
    board_T_world: np.ndarray = field(default_factory=lambda: np.eye(4))  # registration board -> world
    date: str = ""
    board: dict = field(default_factory=dict)  # board geometry the calibration used

    def camera(self, name: str) -> CameraCalibration:
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise CalibrationError(f"calibration has no camera {name!r} (it has {', '.join(self.names())})")

    def names(self) -> list[str]:
        return [cam.name for cam in self.cameras]

    def check_rig(self, rig: dict[str, tuple[int, int]], source: str = "calibration") -> None:
        """Refuse a calibration that does not match a rig given as ``{name: (width, height)}``."""
        missing = sorted(set(rig) - set(self.names()))
        if missing:
            raise CalibrationError(f"{source}: no calibration for camera(s) {', '.join(missing)}; "
                                   f"it calibrates {', '.join(self.names())}: run `xm calibrate` for this rig")
        for name, (width, height) in rig.items():
            cam = self.camera(name)
            if (cam.width, cam.height) != (width, height):
                raise CalibrationError(f"{source}: camera {name} is calibrated at {cam.width}x{cam.height} "
                                       f"but the rig runs it at {width}x{height}: recalibrate or change the "
                                       "deployment's resolution")


def _matrix(value: object, shape: tuple[int, ...], what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{what}: not a numeric array ({exc})") from exc
    if arr.shape != shape:
        raise CalibrationError(f"{what}: shape {arr.shape}, expected {shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{what}: contains NaN or Inf")
    return arr


def to_json(rig: RigCalibration) -> dict:
    return {
        "format": FORMAT,
        "date": rig.date or _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "board": rig.board,
        "board_T_world": rig.board_T_world.tolist(),
        "cameras": [{"name": c.name, "image_size": [c.width, c.height], "K": c.K.tolist(),
                     "dist": c.dist.tolist(), "world_T_cam": c.world_T_cam.tolist(), "rms_px": c.rms_px}
                    for c in rig.cameras],
    }


def from_json(data: dict, source: str = "calibration") -> RigCalibration:
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CalibrationError(f"{source}: not a rig calibration (expected \"format\": \"{FORMAT}\")")
    cams = data.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise CalibrationError(f"{source}: no cameras")
    out = []
    for i, c in enumerate(cams):
        where = f"{source}: cameras[{i}]"
        try:
            name, (width, height) = str(c["name"]), c["image_size"]
            out.append(CameraCalibration(
                name, int(width), int(height), _matrix(c["K"], (3, 3), f"{where}.K"),
                _matrix(c["dist"], (5,), f"{where}.dist"),
                _matrix(c["world_T_cam"], (4, 4), f"{where}.world_T_cam"), float(c.get("rms_px", "nan"))))
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, CalibrationError):
                raise
            raise CalibrationError(f"{where}: {exc!r} (needs name, image_size, K, dist, world_T_cam)") from exc
    board_T_world = _matrix(data.get("board_T_world", np.eye(4).tolist()), (4, 4), f"{source}: board_T_world")
    return RigCalibration(out, board_T_world, str(data.get("date", "")), dict(data.get("board", {})))


def save(rig: RigCalibration, path: str | Path) -> None:
    Path(path).write_text(json.dumps(to_json(rig), indent=1) + "\n")


def load(path: str | Path) -> RigCalibration:
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise CalibrationError(f"{path}: no such calibration file (write one with `xm calibrate`)") from exc
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{path}: not JSON ({exc})") from exc
    return from_json(data, str(path))
