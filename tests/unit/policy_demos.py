"""Small synthetic demonstrations for the policy and baseline tests (not the teacher, no physics).

One hand reaches from a rest pose to an object and carries it to a target while the other sways;
the object start moves with the seed, so start-state conditioning matters. The grasping hand's
thumb and index read 20 kPa while carrying, where the glove is; some samples are occluded.
Shapes follow shared.demo.Demo.
"""

from __future__ import annotations

import numpy as np

from shared.demo import TACTILE_REGIONS, Demo


def synthetic_demo(seed: int, steps: int = 40, objects: int = 4, dt: float = 0.02, split: str = "train",
                   occlude: bool = True, grasp: str | None = None, glove: str = "left") -> Demo:
    """``grasp``: the carrying hand ("left" / "right"; None: drawn with the seed); ``glove``: the
    hand whose tactile is measured."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, steps)[:, None]
    ease = 3 * s ** 2 - 2 * s ** 3
    obj0 = np.array([0.1, 0.0, 0.02]) + rng.uniform(-0.05, 0.05, 3) * [1, 1, 0]
    target = np.array([-0.1, 0.05, 0.02])
    shape = rng.normal(0, 0.01, (21, 3))  # fixed finger layout relative to the wrist
    rest = [np.array([0.0, 0.2, 0.15]), np.array([0.0, -0.2, 0.15])]
    g = int(rng.integers(2)) if grasp is None else ("left", "right").index(grasp)
    reach = np.clip(2 * ease, 0, 1)
    carry = np.clip(2 * ease - 1, 0, 1)
    hands = np.zeros((steps, 2, 21, 3))
    for h in range(2):
        if h == g:
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
        hand_mask[steps // 3: steps // 3 + 3, g, 4:9] = 0
        object_mask[steps // 2: steps // 2 + 4, 0] = 0
    r = len(TACTILE_REGIONS)
    tmask = np.zeros((steps, 2, r), np.uint8)
    tmask[:, ("left", "right").index(glove)] = 1
    tactile = np.zeros((steps, 2, r))
    tactile[:, g, :2] = 20.0 * (carry > 0)
    names = ("left", "right")
    return Demo(dt=dt, hands=hands.astype(np.float32), hand_mask=hand_mask,
                object_names=[f"part/p{k}" for k in range(objects)], objects=objs.astype(np.float32),
                object_mask=object_mask, tactile=(tactile * tmask).astype(np.float32), tactile_mask=tmask,
                phase=["move"] * steps, meta={"task": "synthetic", "seed": seed, "demo": seed, "split": split,
                                              "grasp_hand": names[g], "press_hand": names[1 - g],
                                              "tactile_hand": glove})


def synthetic_protocol(train: int = 3, validation: int = 3, steps: int = 40) -> list[Demo]:
    """A miniature of the Table 7.1 protocol: ``train`` + ``validation`` demos."""
    return [synthetic_demo(i, steps, split="train" if i < train else "validation") for i in range(train + validation)]
