"""The first network's learning curve: its validation score against its training steps, from one run.

Runs the first network's training alone (`xm train --teacher 0 --preset P --threads 1`, as the panel's
first-network job) with a selection rollout from each of the 12 held-out validation layouts every
``--every`` steps from the start (`--select validation --set eval_from=0`), and writes each rollout's
step, seconds and distances (hand, object, and their sum, the score) to
.bench/first_network-curve[-LABEL].json, with the final score and each step's score relative to it.
``--from DIR`` summarises a run already made into DIR (its train.json) instead. The scored weights
are the averaged ones (EMA) the job would keep at that step. Run it under ``nice -n 19``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def curve(info: dict) -> dict:
    evals = [{"step": e["step"], "seconds": round(e["seconds"], 1), "hand_mm": round(e["hand"] * 1e3, 1),
              "object_mm": round(e["object"] * 1e3, 1), "score_mm": round(e["score"] * 1e3, 1)}
             for e in info["evals"]]
    final = evals[-1]["score_mm"]
    for e in evals:
        e["to_final"] = round(e["score_mm"] / final, 3)
    return {"steps": evals[-1]["step"], "seconds": round(info["seconds"], 1), "final_score_mm": final,
            "best_score_mm": min(e["score_mm"] for e in evals),
            "best_step": min(evals, key=lambda e: e["score_mm"])["step"], "evals": evals}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="no_tactile", help="the panel's first_preset")
    parser.add_argument("--steps", type=int, default=None, help="optimizer steps (default: the preset's)")
    parser.add_argument("--every", type=int, default=500, help="steps between selection rollouts")
    parser.add_argument("--from", dest="source", default=None, metavar="DIR", help="summarise DIR/train.json")
    parser.add_argument("--label", default="")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="xm-curve-") as tmp:
        out = Path(args.source) if args.source else Path(tmp)
        if not args.source:
            cmd = [sys.executable, "-m", "shared.cli", "train", "--teacher", "0", "--preset", args.preset,
                   "--threads", "1", "--select", "validation", "--set", "eval_from=0", "--set",
                   f"eval_every={args.every}", "--out", str(out), *(["--steps", str(args.steps)] if args.steps else [])]
            subprocess.run(cmd, check=True, cwd=ROOT)
        res = {"preset": args.preset, **curve(json.loads((out / "train.json").read_text()))}
    (ROOT / ".bench").mkdir(exist_ok=True)
    path = ROOT / f".bench/first_network-curve{'-' + args.label if args.label else ''}.json"
    path.write_text(json.dumps(res, indent=2))
    print(" ".join(f"{e['step']}:{e['score_mm']}" for e in res["evals"]) + f" (mm); final {res['final_score_mm']} mm "
          f"after {res['seconds']} s; {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
