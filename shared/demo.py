"""In-memory form of one demonstration: what the teacher produces and what learning consumes.

Arrays are time-major at a fixed step ``dt``. Hand keypoints follow the MANO/OpenPose order
(0 wrist, 1-4 thumb, 5-8 index, 9-12 middle, 13-16 ring, 17-20 little).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HAND_NAMES = ("left", "right")
KEYPOINTS_PER_HAND = 21
TACTILE_REGIONS = ("thumb", "index", "middle", "ring", "little", "palm")
FINGERTIPS = {"thumb": 4, "index": 8, "middle": 12, "ring": 16, "little": 20}


@dataclass
class Demo:
    """One demonstration. Shapes: T steps, H=2 hands, K object keypoints, R tactile regions."""

    dt: float
    hands: np.ndarray  # (T, H, 21, 3) float32, metres
    hand_mask: np.ndarray  # (T, H, 21) uint8
    object_names: list[str]  # K names "<object>/<point>"
    objects: np.ndarray  # (T, K, 3) float32
    object_mask: np.ndarray  # (T, K) uint8
    tactile: np.ndarray  # (T, H, R) float32, kPa (region mean)
    tactile_mask: np.ndarray  # (T, H, R) uint8, 1 only where a glove measured
    phase: list[str] = field(default_factory=list)  # (T) phase labels
    meta: dict = field(default_factory=dict)  # task, demo index, tactile_hand, grasp_hand, layout

    def __post_init__(self) -> None:
        t = self.hands.shape[0]
        checks = {
            "hands": (self.hands.shape, (t, len(HAND_NAMES), KEYPOINTS_PER_HAND, 3)),
            "hand_mask": (self.hand_mask.shape, (t, len(HAND_NAMES), KEYPOINTS_PER_HAND)),
            "objects": (self.objects.shape, (t, len(self.object_names), 3)),
            "object_mask": (self.object_mask.shape, (t, len(self.object_names))),
            "tactile": (self.tactile.shape, (t, len(HAND_NAMES), len(TACTILE_REGIONS))),
            "tactile_mask": (self.tactile_mask.shape, (t, len(HAND_NAMES), len(TACTILE_REGIONS))),
        }
        for name, (got, want) in checks.items():
            if tuple(got) != want:
                raise ValueError(f"Demo.{name} has shape {tuple(got)}, expected {want}")

    @property
    def steps(self) -> int:
        return int(self.hands.shape[0])

    def save(self, path: str | Path) -> None:
        np.savez_compressed(
            path,
            dt=self.dt,
            hands=self.hands,
            hand_mask=self.hand_mask,
            object_names=np.array(self.object_names),
            objects=self.objects,
            object_mask=self.object_mask,
            tactile=self.tactile,
            tactile_mask=self.tactile_mask,
            phase=np.array(self.phase),
            meta=json.dumps(self.meta),
        )

    @classmethod
    def load(cls, path: str | Path) -> Demo:
        with np.load(path, allow_pickle=False) as z:
            return cls(
                dt=float(z["dt"]),
                hands=z["hands"],
                hand_mask=z["hand_mask"],
                object_names=[str(s) for s in z["object_names"]],
                objects=z["objects"],
                object_mask=z["object_mask"],
                tactile=z["tactile"],
                tactile_mask=z["tactile_mask"],
                phase=[str(s) for s in z["phase"]],
                meta=json.loads(str(z["meta"])),
            )
