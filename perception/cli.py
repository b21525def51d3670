"""``xm detector``: label, train and evaluate the 2-D keypoint detector (thesis 5.6)."""

from __future__ import annotations

import importlib
import sys

SUBCOMMANDS = {
    "label": ("perception.sim_labels:main", "render the simulated rig and write a labelled set (COCO keypoints)"),
    "train": ("perception.train:main", "train the U-Net on a labelled set (runs/detector/; `make detector` ships it)"),
    "train-hands": ("perception.hand_stage:main", "train the second stage on per-hand crops (beside `train`'s output)"),
    "train-objects": ("perception.object_stage:main",
                      "train the object stage on per-object crops (beside `train`'s output)"),
    "quantize": ("perception.quantize:main",
                 "int8 copies of the graphs for ONNX Runtime, calibrated on a labelled set"),
    "eval": ("perception.evaluate:main", "pixel error, PCK@5px, detection under occlusion on held-out images"),
}


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in SUBCOMMANDS:
        asked = not argv or argv[0] in ("-h", "--help")
        out = sys.stdout if asked else sys.stderr
        if not asked:
            print(f"xm detector: unknown subcommand {argv[0]!r}", file=out)
        print("usage: xm detector {label,train,train-hands,train-objects,quantize,eval} [options]\n", file=out)
        for name, (_, text) in SUBCOMMANDS.items():
            print(f"  {name:<13} {text}", file=out)
        return 0 if asked else 2
    module, func = SUBCOMMANDS[argv[0]][0].split(":")
    return int(getattr(importlib.import_module(module), func)(argv[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
