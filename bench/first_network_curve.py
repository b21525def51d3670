"""The first network's learning curve: its validation score against its training steps, from one run.

Runs the first network's training alone (`xm train --teacher 0 --preset P --threads 1`, as the panel's
first-network job) with a selection rollout from each of the 12 held-out validation layouts every
``--every`` steps from the start (`--select validation --set eval_from=0`), and writes each rollout's
step, seconds and distances (hand, object, and their sum, the score) to
.bench/first_network-curve[-LABEL].json, with the final score and each step's score relative to it.
``--from DIR`` summarises a run already made into DIR (its train.json) instead, ``--from FILE`` the
progress file (`xm train --progress`) of a run stopped before its end (no seconds, no final score).
The scored weights are the averaged ones (EMA) the job would keep at that step. Run it under
``nice -n 19``.
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
    """``info``: a train.json, or ``{"evals": [...], "stopped_at": step}`` read from a progress file."""
    evals = [{"step": e["step"], "seconds": round(e["seconds"], 1) if "seconds" in e else None,
              "hand_mm": round(e["hand"] * 1e3, 1), "object_mm": round(e["object"] * 1e3, 1),
              "score_mm": round(e["score"] * 1e3, 1)} for e in info["evals"]]
    res = {"steps": info.get("stopped_at", evals[-1]["step"]), "seconds": info.get("seconds"),
           "best_score_mm": min(e["score_mm"] for e in evals),
           "best_step": min(evals, key=lambda e: e["score_mm"])["step"], "evals": evals}
    if "stopped_at" not in info:
        res["final_score_mm"] = final = evals[-1]["score_mm"]
        for e in evals:
            e["to_final"] = round(e["score_mm"] / final, 3)
    return res


def read_progress(path: Path) -> dict:
    records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return {"evals": [{"step": r["step"], **r["eval"]} for r in records if "eval" in r],
            "stopped_at": max(r["step"] for r in records), "steps_planned": records[0].get("steps")}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="no_tactile", help="the panel's first_preset")
    parser.add_argument("--steps", type=int, default=None, help="optimizer steps (default: the preset's)")
    parser.add_argument("--every", type=int, default=500, help="steps between selection rollouts")
    parser.add_argument("--from", dest="source", default=None, metavar="DIR|FILE",
                        help="summarise DIR/train.json, or a progress file of a stopped run")
    parser.add_argument("--label", default="")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="xm-curve-") as tmp:
        out = Path(args.source) if args.source else Path(tmp)
        if not args.source:
            cmd = [sys.executable, "-m", "shared.cli", "train", "--teacher", "0", "--preset", args.preset,
                   "--threads", "1", "--select", "validation", "--set", "eval_from=0", "--set",
                   f"eval_every={args.every}", "--out", str(out), *(["--steps", str(args.steps)] if args.steps else [])]
            subprocess.run(cmd, check=True, cwd=ROOT)
        info = read_progress(out) if out.is_file() else json.loads((out / "train.json").read_text())
        res = {"preset": args.preset, **({"steps_planned": info["steps_planned"]} if out.is_file() else {}),
               **curve(info)}
    (ROOT / ".bench").mkdir(exist_ok=True)
    path = ROOT / f".bench/first_network-curve{'-' + args.label if args.label else ''}.json"
    path.write_text(json.dumps(res, indent=2))
    print(" ".join(f"{e['step']}:{e['score_mm']}" for e in res["evals"]) + f" (mm); final "
          f"{res.get('final_score_mm', '(stopped)')} mm after {res['seconds']} s; {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
