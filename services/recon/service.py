"""recon node: on each synchronized frame set, detect 2-D keypoints per camera, triangulate, and
publish the scene with the latest tactile region pressures of each glove."""

from __future__ import annotations

import collections
from dataclasses import dataclass

import numpy as np

from services.glove.layout import region_means
from services.recon.detector import CameraModel, SimulatedDetector, readout_window
from services.recon.scene import split_points, tactile_matrix
from services.recon.triangulation import triangulate
from shared import msgs
from shared.demo import TACTILE_REGIONS
from shared.runtime import Node

TACTILE_MAX_AGE_S = 0.5


class ReconService:
    @dataclass
    class Params:
        detector: str = "simulated"
        pixel_noise: float = 1.0
        dropout: float = 0.08
        seed: int = 0

    def __init__(self, node: Node, params: Params) -> None:
        if params.detector != "simulated":
            raise ValueError(f"recon detector {params.detector!r}: only 'simulated' exists in this build")
        self.node = node
        self.detector = SimulatedDetector(params.pixel_noise, params.dropout, params.seed)
        self.cameras: dict[str, CameraModel] = {}
        self.truth: collections.deque = collections.deque(maxlen=64)  # (stamp, msg)
        self.tactile: dict[str, tuple[float, np.ndarray]] = {}
        self.scene_pub = node.output("scene")
        node.input("info", self.on_info)
        node.input("truth", self.on_truth)
        node.input("tactile", self.on_tactile)
        node.input("frame", self.on_frame)  # the first camera's image marks a triggered frame set

    def on_info(self, msg, key: str) -> None:
        self.cameras[key.split("/")[2]] = CameraModel(np.asarray(msg.p, float).reshape(3, 4), msg.width, msg.height,
                                                      readout_window(msg))

    def on_truth(self, msg) -> None:
        self.truth.append((msgs.stamp_seconds(msg.header.stamp), msg))

    def on_tactile(self, msg) -> None:
        pressure = np.asarray(msg.pressure, np.float32).reshape(msg.rows, msg.cols)
        self.tactile[msg.hand] = (msgs.stamp_seconds(msg.header.stamp), region_means(pressure))

    def on_frame(self, msg) -> None:
        stamp = msgs.stamp_seconds(msg.header.stamp)
        if not self.truth or len(self.cameras) < 2:
            return
        _, truth = min(self.truth, key=lambda st: abs(st[0] - stamp))
        hand_names = list(truth.hand_names)
        points = np.concatenate([np.asarray(truth.hand_keypoints, float).reshape(-1, 3),
                                 np.asarray(truth.object_keypoints, float).reshape(-1, 3)])
        visible = np.concatenate([np.asarray(truth.hand_visible), np.asarray(truth.object_visible)]) \
            if len(truth.hand_visible) else None
        cams = [self.cameras[c] for c in sorted(self.cameras)]
        uv, seen = self.detector.detect(cams, points, visible)
        tri, mask = triangulate(np.stack([c.P for c in cams]), uv, seen)
        hands, hand_mask, objects, object_mask = split_points(tri, mask, len(hand_names))
        fresh = {h: v for h, (t, v) in self.tactile.items() if abs(stamp - t) < TACTILE_MAX_AGE_S}
        tactile, tactile_mask = tactile_matrix(hand_names, fresh)
        self.scene_pub.put(msgs.make(
            "xm_msgs/msg/Scene", header=msgs.header(stamp, "world"), hand_names=hand_names,
            hand_keypoints=hands.astype(np.float32).ravel(), hand_mask=hand_mask.ravel(),
            object_names=list(truth.object_names), object_keypoints=objects.astype(np.float32).ravel(),
            object_mask=object_mask.ravel(), tactile_regions=list(TACTILE_REGIONS),
            tactile=tactile.ravel(), tactile_mask=tactile_mask.ravel()))
