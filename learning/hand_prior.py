"""Writes the hand-pose prior table the trajopt service reads (thesis 7.22, services/trajopt/hand_prior.py)
from the scripted teacher's demonstrations: ``python -m learning.hand_prior [--task T] [--demos N]``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.trajopt.hand_prior import DEFAULT_PRIOR, prior_table
from services.world.teacher import generate_demo

TASK, DEMOS = "assembly", 2  # the shipped table's source


def teacher_table(task: str = TASK, demos: int = DEMOS) -> dict:
    """The prior table of the scripted teacher's demonstrations of ``task``, seeds 1..``demos``."""
    return prior_table([generate_demo(task, seed) for seed in range(1, demos + 1)],
                       f"scripted teacher, {demos} {task} demonstrations (seeds 1-{demos})")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--task", default=TASK, help="the scripted teacher's task (default %(default)s)")
    ap.add_argument("--demos", type=int, default=DEMOS, help="demonstrations, seeds 1..N (default %(default)s)")
    ap.add_argument("--out", type=Path, default=DEFAULT_PRIOR, help="where to write it (default %(default)s)")
    args = ap.parse_args(argv)
    table = teacher_table(args.task, args.demos)
    args.out.write_text(json.dumps(table, indent=1, sort_keys=True) + "\n")
    print(f"wrote {args.out}: {len(table['right']['mean'])} joints per hand from {table['frames']} frames")


if __name__ == "__main__":
    main()
