"""The first network trained beside the running cell: how long until it is served, and where the time goes.

`xm up deploy/sim.toml` with its router, run directory, dashboard port, recordings and the policy's
checkpoint private to a temporary directory, so the panel starts the first-network job (`xm train
--teacher 0`, the page's job runner) exactly as on a fresh install, while the whole cell runs. Every
``--sample-s`` seconds it reads the job's progress file and the CPU time of the cell's processes (the
`xm up` process group) and of the job's (its own group), and the host's load. It ends when the policy
service serves the new checkpoint (or at ``--timeout-min``) and reports: seconds from the job's start
to its best rollout score (train.json ``seconds_to_best``), to the checkpoint and to the policy
serving it; the training step rate; the CPU cores the cell and the job used; the host load. Writes
.bench/first_network[-LABEL].json. Target: the first network at its best score within 15 minutes.

Compare settings in one sitting, e.g. ``--threads 2 --label baseline`` then ``--threads 1``: the
host's load decides much of the figure, so report the load beside it. Run it under ``nice -n 19``
on a shared host (the cell and the job alike).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # runnable as a script from anywhere

from tests.conftest import free_endpoint, free_port, query_router, xm_up  # noqa: E402

TARGET_S = 15 * 60
TICK = os.sysconf("SC_CLK_TCK")


def deployment(tmp: Path, threads: int, preset: str, steps: int | None, train_args: str) -> tuple[Path, str, Path]:
    """deploy/sim.toml with everything private to ``tmp``; the first network trains into tmp/policy."""
    text = (ROOT / "deploy/sim.toml").read_text()
    router = free_endpoint()
    checkpoint = tmp / "policy" / "policy.pt"
    text = re.sub(r'router = "[^"]*"', f'router = "{router}"', text)
    text = re.sub(r'run_dir = "[^"]*"', f'run_dir = "{tmp}/run"', text)
    text = re.sub(r'checkpoint = "[^"]*"', f'checkpoint = "{checkpoint}"', text)
    text = re.sub(r"port = 8080", f"port = {free_port()}", text)
    text = re.sub(r'directory = "[^"]*"', f'directory = "{tmp}/recordings"', text)
    text = re.sub(r'first_network = "[^"]*"',
                  f'first_network = "{checkpoint}"\nfirst_preset = "{preset}"\ntrain_threads = {threads}\n'
                  + (f"first_steps = {steps}\n" if steps is not None else "") +
                  f'models = "{tmp}/models"\ntrain_args = "{train_args}"', text)
    path = tmp / "sim.toml"
    path.write_text(text)
    return path, router, checkpoint


def cpu_seconds(root: int, job: int | None) -> tuple[float, float]:
    """User + system CPU seconds of the live processes under ``root`` (the services run in process
    groups of their own): (the cell's, the job's), the job being the process group ``job``."""
    stats = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()  # after the name: state, ppid, pgrp, ...
        except OSError:
            continue
        stats[int(stat.parent.name)] = (int(fields[1]), int(fields[2]), (int(fields[11]) + int(fields[12])) / TICK)
    children: dict[int, list[int]] = {}
    for pid, (ppid, _, _) in stats.items():
        children.setdefault(ppid, []).append(pid)
    cell = job_s = 0.0
    todo = [root]
    while todo:
        pid = todo.pop()
        if pid in stats:
            if stats[pid][1] == job:
                job_s += stats[pid][2]
            else:
                cell += stats[pid][2]
        todo += children.get(pid, [])
    return cell, job_s


def progress(path: Path) -> list[dict]:
    try:
        return [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()]
    except (OSError, ValueError):
        return []


def load() -> float:
    return float(Path("/proc/loadavg").read_text().split()[0])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--threads", type=int, default=1, help="torch threads of the job (the panel's train_threads)")
    parser.add_argument("--preset", default="no_tactile", help="the job's preset (the panel's first_preset)")
    parser.add_argument("--steps", type=int, default=None,
                        help="the job's optimizer steps (the panel's first_steps; default: the panel's default)")
    parser.add_argument("--train-args", default="", help="more `xm train` options (the panel's train_args)")
    parser.add_argument("--timeout-min", type=float, default=40.0)
    parser.add_argument("--sample-s", type=float, default=5.0)
    parser.add_argument("--label", default="", help="suffix of the result file")
    args = parser.parse_args(argv)
    ended = []  # SIGTERM: stop measuring, stop the cell, report what was measured
    signal.signal(signal.SIGTERM, lambda *_: ended.append(True))
    samples: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="xm-first-") as tmp_name:
        tmp = Path(tmp_name)
        dep, router, checkpoint = deployment(tmp, args.threads, args.preset, args.steps, args.train_args)
        partial = checkpoint.parent / ".job.partial"
        t_up = time.monotonic()
        with xm_up(dep, tmp / "up.log") as proc:
            job_pid, t_job, served_at, last = None, None, None, (None, None, None)
            deadline = t_up + args.timeout_min * 60
            while time.monotonic() < deadline and proc.poll() is None and not ended:
                time.sleep(args.sample_s)
                now = time.monotonic()
                if job_pid is None:
                    try:
                        job_pid, t_job = int((partial / "job.pid").read_text()), now
                    except (OSError, ValueError):
                        pass
                cell, job = cpu_seconds(proc.pid, job_pid)
                recs = progress(partial / "progress.jsonl")
                step = max((r.get("step", 0) for r in recs), default=0)
                if last[0] is not None:
                    dt = now - last[0]
                    samples.append({"t": round(now - (t_job or now), 1), "step": step, "load": load(),
                                    "cell_cores": round((cell - last[1]) / dt, 3),
                                    "job_cores": round(max(0.0, job - last[2]) / dt, 3)})
                    print(json.dumps(samples[-1]), flush=True)
                last = (now, cell, job)
                policy = [r for r in query_router(router, "xm/policy/main/@health") if r.get("instance") == "main"]
                served = policy and policy[0].get("checkpoint") == str(checkpoint)
                if served and str(policy[0].get("method")).startswith("learned"):  # "learned:PRESET"
                    served_at = now
                    break
            up_log = (tmp / "up.log").read_text(errors="replace")
        info_path = checkpoint.parent / "train.json"
        info = json.loads(info_path.read_text()) if info_path.exists() else {}
        written_at = checkpoint.stat().st_mtime if checkpoint.exists() else None
        job_started_wall = (partial / "job.pid").stat().st_mtime if (partial / "job.pid").exists() else None
    training = [s for s in samples if s["job_cores"] > 0]
    steps_per_s = None
    if len(training) >= 2 and training[-1]["t"] > training[0]["t"]:
        steps_per_s = (training[-1]["step"] - training[0]["step"]) / (training[-1]["t"] - training[0]["t"])
    res = {
        "target_s": TARGET_S, "threads": args.threads, "preset": args.preset, "train_args": args.train_args,
        "steps_budget": args.steps, "steps_reached": max((s["step"] for s in samples), default=None),
        "served": served_at is not None,
        "seconds_job_to_served": None if served_at is None or t_job is None else round(served_at - t_job, 1),
        "train_seconds": info.get("seconds"), "seconds_to_best": info.get("seconds_to_best"),
        "best_score_mm": None if "best_score_m" not in info else round(info["best_score_m"] * 1e3, 1),
        "best_step": info.get("best_step"), "evals": info.get("evals"),
        "checkpoint_after_job_start_s": None if written_at is None or job_started_wall is None
        else round(written_at - job_started_wall, 1),
        "steps_per_s": None if steps_per_s is None else round(steps_per_s, 2),
        "cell_cores_median": round(statistics.median(s["cell_cores"] for s in samples), 2) if samples else None,
        "job_cores_median": round(statistics.median(s["job_cores"] for s in training), 2) if training else None,
        "load_median": round(statistics.median(s["load"] for s in samples), 2) if samples else None,
        "load_range": [min(s["load"] for s in samples), max(s["load"] for s in samples)] if samples else None,
        "nice": os.nice(0), "samples": samples,
    }
    res["met"] = bool(res["seconds_to_best"] is not None and res["seconds_to_best"] <= TARGET_S)
    (ROOT / ".bench").mkdir(exist_ok=True)
    out = ROOT / f".bench/first_network{'-' + args.label if args.label else ''}.json"
    out.write_text(json.dumps(res, indent=2, default=float))
    if served_at is None:
        print(f"not served within {args.timeout_min:g} min; xm up log tail:\n{up_log[-2000:]}", file=sys.stderr)
    print(f"threads {args.threads}, preset {args.preset}: best score {res['best_score_mm']} mm after "
          f"{res['seconds_to_best']} s of training, served {res['seconds_job_to_served']} s after the job started; "
          f"{res['steps_per_s']} steps/s; cell {res['cell_cores_median']} cores, job {res['job_cores_median']}; "
          f"load {res['load_median']} {res['load_range']}; {out}")
    return 0 if served_at is not None else 1


if __name__ == "__main__":
    raise SystemExit(main())
