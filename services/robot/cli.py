"""`xm robot repeatability`: table 6.1 of the thesis, measured on the simulated robot."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.robot.repeatability import run

THESIS = {"Y": (0.03, 0.009), "Z": (0.05, 0.015), "Wrist": (0.014, 0.0047), "Gripper": (0.02, 0.0065),
          "X, Y, Z": (0.07, 0.023)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="xm robot", description="Robot tools.")
    sub = parser.add_subparsers(dest="cmd", required=True)
    rep = sub.add_parser("repeatability", help="table 6.1 in simulation (virtual dial gauge)")
    rep.add_argument("--seed", type=int, default=0)
    rep.add_argument("--out", default="runs/repeatability.json")
    args = parser.parse_args(argv)
    results = run(args.seed)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2))
    print(f"{'joints':<10}{'end-effector':<14}{'3 sigma':>10}{'1 sigma':>10}   thesis 3s / 1s")
    for r in results:
        ref = THESIS.get(r["joints"], (float("nan"),) * 2)
        print(f"{r['joints']:<10}{r['end_effector']:<14}{r['three_sigma_mm']:>8.4f}mm{r['sigma_mm']:>8.4f}mm   "
              f"{ref[0]} / {ref[1]} mm")
    print(f"wrote {args.out}")
    return 0
