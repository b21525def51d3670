"""Why the learned policy alone misses the assembly's contacts:
`python -m evaluation.contact_diagnosis CHECKPOINT [--seed S]`.

Neural simulations of an assembly net (no robot, no training), per demonstration of the seed's
protocol (3 training, 12 validation):

- **reach**: the grasping hand's start distance to the lens (horizontal) and, open loop from the
  start state, the closest approach of its pinch to the lens and of the module's connector to the
  board's; the same on the demonstration's mirror image (y -> -y, hands swapped: what training's
  mirroring adds), which separates the hand from the length of its reach;
- **fit**: on the training demonstrations, with the objects moved as the teacher moved them, the
  pinch's closest approach to the lens within 1 s of the teacher's grasp (how well the net
  reproduces what it was trained on);
- **touch by visibility**: the largest predicted grasping touch (thumb + index) over the
  simulation when every hand and object point is given back as seen (a robot loop observing the
  objects' truth) against the net's own predicted visibility (the neural simulation), both with
  the net's predicted touch given back on the demonstration's gloved hand.
"""

from __future__ import annotations

import argparse

import numpy as np

from evaluation.anchors import pinch
from learning.dataset import mirror
from services.policy.model import Policy
from services.policy.runner import PolicyRunner, SceneObs, simulate
from services.world.teacher import assembly_protocol
from shared.demo import KEYPOINTS_PER_HAND, TACTILE_REGIONS, Demo

N_TRAIN = 3
FIT_WINDOW = 50  # samples either side of the teacher's grasp (1 s at 0.02 s)
TOUCH_STEPS = 400  # 8 s of neural simulation
THUMB, INDEX = TACTILE_REGIONS.index("thumb"), TACTILE_REGIONS.index("index")


def grasp_index(demo: Demo) -> int:
    return 0 if demo.meta["grasp_hand"] == "left" else 1


def reach(model: Policy, demo: Demo) -> dict:
    """Open loop from ``demo``'s start: reach (cm), pinch-to-lens and connector gap (mm)."""
    names = demo.object_names
    lens, conn, board = (names.index(n) for n in ("camera/lens", "camera/connector", "board/connector"))
    g = grasp_index(demo)
    r = simulate(model, demo, len(demo.objects))
    return {"reach_cm": float(np.linalg.norm(demo.hands[0, g, 0, :2] - demo.objects[0, lens, :2]) * 100),
            "pinch_mm": float(np.linalg.norm(pinch(r.hands[:, g]) - r.objects[:, lens], axis=-1).min() * 1e3),
            "connector_mm": float(np.linalg.norm(r.objects[:, conn] - r.objects[:, board], axis=-1).min() * 1e3)}


def fit(model: Policy, demo: Demo) -> float:
    """Pinch-to-lens (mm) within FIT_WINDOW of the teacher's grasp, objects as the teacher moved them."""
    lens = demo.object_names.index("camera/lens")
    g = grasp_index(demo)
    r = simulate(model, demo, len(demo.objects), observed_objects=demo.objects)
    tg = int(np.argmin(np.linalg.norm(pinch(demo.hands[:, g]) - demo.objects[:, lens], axis=-1)))
    miss = np.linalg.norm(pinch(r.hands[:, g]) - demo.objects[:, lens], axis=-1)
    return float(miss[max(0, tg - FIT_WINDOW):tg + FIT_WINDOW].min() * 1e3)


def touch(model: Policy, demo: Demo, all_seen: bool) -> float:
    """Largest predicted grasping touch (kPa) over TOUCH_STEPS of neural simulation through the
    runner, every point given back as seen (``all_seen``) or with the net's predicted visibility."""
    g, n = grasp_index(demo), 2 * KEYPOINTS_PER_HAND
    runner = PolicyRunner(model, glove=demo.tactile_mask[0].any(-1).astype(bool))
    seen = np.ones(n + model.K, bool)
    scene = SceneObs(demo.hands[0].astype(float), demo.hand_mask[0].astype(bool), demo.objects[0].astype(float),
                     demo.object_mask[0].astype(bool))
    if all_seen:
        scene.hand_mask[:], scene.object_mask[:] = True, True
    peak = 0.0
    for _ in range(TOUCH_STEPS):
        nxt = runner.step(scene)
        mask = seen if all_seen else runner.predicted["mask"]
        scene = SceneObs(nxt[:n].reshape(2, KEYPOINTS_PER_HAND, 3), mask[:n].reshape(2, KEYPOINTS_PER_HAND),
                         nxt[n:], mask[n:])
        peak = max(peak, float(runner.efforts[g, THUMB] + runner.efforts[g, INDEX]))
    return peak


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m evaluation.contact_diagnosis", description=__doc__.split("\n")[0])
    parser.add_argument("checkpoint", help="an assembly net (policy_multimodal.pt of `xm eval`)")
    parser.add_argument("--seed", type=int, default=0, help="the protocol's layout seed")
    args = parser.parse_args(argv)
    model = Policy.load(args.checkpoint)
    print("| demo | split | grasp | reach cm | pinch mm | connector mm | mirrored: grasp | pinch mm | connector mm "
          "| fit mm | touch kPa all seen / own visibility |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for demo in assembly_protocol(args.seed):
        train = demo.meta["demo"] < N_TRAIN
        real, mirrored = reach(model, demo), reach(model, mirror(demo))
        fitted = f"{fit(model, demo):.1f}" if train else ""
        kpa = f"{touch(model, demo, True):.0f} / {touch(model, demo, False):.0f}"
        print(f"| {demo.meta['demo']} | {'train' if train else 'validation'} | {demo.meta['grasp_hand']} "
              f"| {real['reach_cm']:.1f} | {real['pinch_mm']:.1f} | {real['connector_mm']:.1f} "
              f"| {'right' if demo.meta['grasp_hand'] == 'left' else 'left'} | {mirrored['pinch_mm']:.1f} "
              f"| {mirrored['connector_mm']:.1f} | {fitted} | {kpa} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
