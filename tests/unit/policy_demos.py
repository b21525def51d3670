"""Small synthetic demonstrations for tests (simulated: not the teacher, no physics).

Both hands reach from a rest pose to an object point, the object is carried to a target; the
object start moves with the seed, so start-state conditioning matters. Some samples are
marked occluded. Shapes follow shared.demo.Demo.
"""

from __future__ import annotations

import numpy as np

from shared.demo import TACTILE_REGIONS, Demo


def synthetic_demo(seed: int, steps: int = 40, objects: int = 4, dt: float = 0.05, split: str = "train",
                   occlude: bool = True) -> Demo:
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, steps)[:, None]
    ease = 3 * s ** 2 - 2 * s ** 3
    obj0 = np.array([0.1, 0.0, 0.02]) + rng.uniform(-0.05, 0.05, 3) * [1, 1, 0]
    target = np.array([-0.1, 0.05, 0.02])
    shape = rng.normal(0, 0.01, (21, 3))  # fixed finger layout relative to the wrist
    rest = [np.array([0.0, 0.2, 0.15]), np.array([0.0, -0.2, 0.15])]
    grasp = rng.integers(2)
    reach = np.clip(2 * ease, 0, 1)
    carry = np.clip(2 * ease - 1, 0, 1)
    hands = np.zeros((steps, 2, 21, 3))
    for h in range(2):
        if h == grasp:
            path = rest[h] + reach * (obj0 + [0, 0, 0.03] - rest[h]) + carry * (target - obj0)
        else:
            path = rest[h] + 0.02 * np.sin(2 * np.pi * s) * [1, 0, 0]
        hands[:, h] = path[:, None] + shape
    offsets = np.array([[0.01 * k, 0.005 * k, 0.0] for k in range(objects)])
    obj = obj0 + carry * (target - obj0)
    objs = obj[:, None] + offsets
    hand_mask = np.ones((steps, 2, 21), np.uint8)
    object_mask = np.ones((steps, objects), np.uint8)
    if occlude:
        hand_mask[steps // 3: steps // 3 + 3, grasp, 4:9] = 0
        object_mask[steps // 2: steps // 2 + 4, 0] = 0
    r = len(TACTILE_REGIONS)
    return Demo(dt=dt, hands=hands.astype(np.float32), hand_mask=hand_mask, object_names=[f"part/p{k}" for k in
                range(objects)], objects=objs.astype(np.float32), object_mask=object_mask,
                tactile=np.zeros((steps, 2, r), np.float32), tactile_mask=np.zeros((steps, 2, r), np.uint8),
                phase=["move"] * steps, meta={"task": "synthetic", "seed": seed, "demo": seed, "split": split,
                                              "grasp_hand": ("left", "right")[grasp],
                                              "press_hand": ("right", "left")[grasp], "tactile_hand": "left"})


def synthetic_protocol(train: int = 3, validation: int = 3, steps: int = 40) -> list[Demo]:
    """A miniature of the Table 7.1 protocol: ``train`` + ``validation`` demos."""
    return [synthetic_demo(i, steps, split="train" if i < train else "validation") for i in range(train + validation)]
