"""Byte format of a synchronized frame set from the simulated camera rig (world -> camhub).

One reply carries every camera triggered together: a little-endian u32 length, a JSON header
(stamp, and per camera name, width, height, K, world_T_cam), then the raw RGB frames in order.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass

import numpy as np


class FrameSetError(ValueError):
    """Bytes that are not a frame set."""


@dataclass
class CameraFrame:
    name: str
    K: np.ndarray  # (3,3) OpenCV intrinsics
    world_T_cam: np.ndarray  # (4,4) camera pose, OpenCV axes (x right, y down, z forward)
    image: np.ndarray  # (H,W,3) uint8 RGB


def pack(stamp: float, frames: list[CameraFrame]) -> bytes:
    header = {"stamp": stamp, "cameras": [
        {"name": f.name, "width": int(f.image.shape[1]), "height": int(f.image.shape[0]),
         "K": f.K.tolist(), "world_T_cam": f.world_T_cam.tolist()} for f in frames]}
    head = json.dumps(header).encode()
    return struct.pack("<I", len(head)) + head + b"".join(np.ascontiguousarray(f.image).tobytes() for f in frames)


def unpack(data: bytes) -> tuple[float, list[CameraFrame]]:
    if len(data) < 4:
        raise FrameSetError(f"frame set of {len(data)} bytes is too short")
    (n,) = struct.unpack_from("<I", data)
    try:
        header = json.loads(data[4:4 + n])
        offset = 4 + n
        frames = []
        for cam in header["cameras"]:
            w, h = int(cam["width"]), int(cam["height"])
            size = w * h * 3
            if offset + size > len(data):
                raise FrameSetError(f"frame set truncated in camera {cam['name']}")
            image = np.frombuffer(data, np.uint8, size, offset).reshape(h, w, 3)
            offset += size
            frames.append(CameraFrame(cam["name"], np.array(cam["K"], float),
                                      np.array(cam["world_T_cam"], float), image))
        return float(header["stamp"]), frames
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, FrameSetError):
            raise
        raise FrameSetError(f"bad frame set header: {exc}") from exc
