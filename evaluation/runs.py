"""Provenance of `xm eval` runs and their summary over seeds and training draws.

Every run writes ``run.json`` beside its results: the task, seed, draw, budget, observations,
recipe changes and, per row, the version of the code that produced it (a hash of that row's
sources, the protocol's sources and the numeric libraries). ``check_merge`` refuses to keep rows of
an earlier run that differs in any of these; ``summarize`` refuses to pool runs of different tasks
or code versions, and reports per row the mean and spread over runs and the paired ratio of each
row to ours (row 1), run by run.
"""

from __future__ import annotations

import hashlib
import json
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np

from learning.metrics import SCORE_KEYS

ROOT = Path(__file__).resolve().parent.parent
# what produces the demonstrations and the score of every row
PROTOCOL_SOURCES = ("learning/metrics.py", "services/world", "shared/demo.py", "evaluation/evaluate.py")
OURS_SOURCES = ("learning", "services/policy")
ROW_SOURCES = {
    "multimodal": OURS_SOURCES, "no_tactile": OURS_SOURCES, "single_state": OURS_SOURCES,
    "time_window": OURS_SOURCES,
    "dmp": ("evaluation/baselines/dmp.py", "services/policy/flat_state.py"),
    "promp_conditional": ("evaluation/baselines/promp.py", "services/policy/flat_state.py"),
    "promp_simple": ("evaluation/baselines/promp.py", "services/policy/flat_state.py"),
    # LeRobot's version: its pins (the package directory beside the venv, interop/lerobot_site.py)
    "diffusion_unet": ("evaluation/baselines/lerobot_diffusion.py", "evaluation/baselines/curve.py",
                       "interop/lerobot_site.py", "tests/lerobot_check/requirements.txt",
                       "services/policy/flat_state.py"),
    "diffusion_transformer": ("evaluation/baselines/diffusion_policy.py", "evaluation/baselines/diffusion_nets.py",
                              "evaluation/baselines/curve.py", "services/policy/flat_state.py"),
    "naive": ("services/policy/naive.py", "services/policy/flat_state.py"),
}
LIBRARIES = ("torch", "numpy", "diffusers", "movement_primitives")
OURS = "multimodal"
# settings that make two runs different experiments (the seed and draw are checked on merge only)
SETTINGS = ("task", "quick", "observations", "changes")


class RunError(ValueError):
    """Runs that must not be merged or pooled, or a run folder without its provenance."""


def _files(rel: str) -> list[Path]:
    path = ROOT / rel
    return sorted(path.rglob("*.py")) if path.is_dir() else [path]


def sources_digest(rels: tuple[str, ...] | list[str]) -> Any:
    """A running SHA-256 over the named files and folders' Python sources (paths and contents)."""
    h = hashlib.sha256()
    for rel in rels:
        for f in _files(rel):
            h.update(str(f.relative_to(ROOT)).encode())
            h.update(f.read_bytes() if f.exists() else b"<missing>")
    return h


def code_version(method: str, reconstructed: bool = False) -> str:
    """12 hex digits: the hash of ``method``'s sources, the protocol's and the libraries' versions."""
    h = sources_digest(PROTOCOL_SOURCES + ROW_SOURCES.get(method, ())
                       + (("evaluation/reconstructed.py",) if reconstructed else ()))
    for lib in LIBRARIES:
        try:
            h.update(f"{lib}=={version(lib)}".encode())
        except PackageNotFoundError:
            h.update(f"{lib} absent".encode())
    return h.hexdigest()[:12]


def run_meta(task: str, seed: int, draw: int, quick: bool, observations: str, changes: dict | None,
             methods: list[str] | tuple[str, ...]) -> dict:
    return {"task": task, "seed": seed, "draw": draw, "quick": quick, "observations": observations,
            "changes": {k: list(v) if isinstance(v, tuple) else v for k, v in (changes or {}).items()},
            "versions": {m: code_version(m, observations != "truth") for m in methods}, "failed": {}}


def read_meta(out: Path) -> dict:
    path = out / "run.json"
    if not path.exists():
        raise RunError(f"{out} has results but no run.json (their seed, task and code version are unknown): "
                       f"run them again into an empty folder")
    return json.loads(path.read_text())


def check_merge(out: Path, meta: dict, kept: list[str]) -> dict:
    """The earlier run's metadata in ``out`` if its rows ``kept`` may share a table with this run
    (``meta``); RunError naming every difference otherwise."""
    old = read_meta(out)
    problems = [f"{k} {old.get(k)!r} here, {meta[k]!r} now" for k in ("seed", "draw") + SETTINGS
                if old.get(k) != meta[k]]
    for m in kept:
        then, now = old.get("versions", {}).get(m), code_version(m, meta["observations"] != "truth")
        if then != now:
            problems.append(f"row {m} from code version {then}, the code is now {now}")
    if problems:
        raise RunError(f"--merge refused: {out} holds another experiment ({'; '.join(problems)}); "
                       f"use another --out or run every row again")
    return old


def summarize(runs: list[Path]) -> dict:
    """Mean and spread per row and column over ``runs`` (folders of one experiment each), and per
    row the paired ratio row / ours over the runs holding both."""
    metas = [read_meta(r) for r in runs]
    results = [json.loads((r / "results.json").read_text()) for r in runs]
    first = metas[0]
    for r, m in zip(runs, metas, strict=True):
        diff = [k for k in SETTINGS if m.get(k) != first.get(k)]
        if diff:
            raise RunError(f"{r} differs from {runs[0]} in {', '.join(diff)}: not one experiment")
    rows: dict[str, dict] = {}
    for name in dict.fromkeys(k for res in results for k in res):
        versions = {m["versions"].get(name) for m, res in zip(metas, results, strict=True) if name in res}
        if len(versions) > 1:
            raise RunError(f"row {name} comes from code versions {sorted(map(str, versions))}: not pooled")
        runs_of = [(m, res[name]) for m, res in zip(metas, results, strict=True) if name in res]
        failed = [f"seed {m['seed']} draw {m['draw']}: {m['failed'][name]}" for m, _ in runs_of
                  if name in m.get("failed", {})]
        row = {"n": len(runs_of), "version": versions.pop(), "failed": failed, "runs": [
            {"seed": m["seed"], "draw": m["draw"], **r} for m, r in runs_of]}
        for k in SCORE_KEYS:
            x = np.array([r[k] for _, r in runs_of], dtype=float)
            row[k] = {"mean": float(np.mean(x)), "std": float(np.std(x, ddof=1)) if len(x) > 1 else float("nan"),
                      "min": float(np.min(x)), "max": float(np.max(x))}
            if name != OURS:
                row[k]["ratio"] = paired_ratio(results, name, k)
        rows[name] = row
    best = {}
    baselines = [n for n in rows if n not in ("multimodal", "no_tactile")]
    for k in SCORE_KEYS:
        finite = [n for n in baselines if np.isfinite(rows[n][k]["mean"])]
        if finite and OURS in rows:
            b = min(finite, key=lambda n: rows[n][k]["mean"])
            best[k] = {"row": b, **rows[b][k]["ratio"]}
    return {"task": first["task"], "quick": first["quick"], "observations": first["observations"],
            "changes": first["changes"], "runs": [{"seed": m["seed"], "draw": m["draw"]} for m in metas],
            "rows": rows, "best_baseline": best}


def paired_ratio(results: list[dict], name: str, key: str) -> dict:
    """Row ``name`` / ours on column ``key`` in every run holding both: mean, spread (sample
    standard deviation) and count; ``within_spread``: 1 lies within mean +- spread (or n < 2)."""
    r = np.array([res[name][key] / res[OURS][key] for res in results
                  if name in res and OURS in res and res[OURS][key] > 0], dtype=float)
    if not len(r) or not np.isfinite(r).all():
        return {"mean": float("inf") if len(r) else float("nan"), "std": float("nan"), "n": int(len(r)),
                "within_spread": False}
    std = float(np.std(r, ddof=1)) if len(r) > 1 else float("nan")
    within = bool(len(r) < 2 or abs(float(np.mean(r)) - 1.0) <= std)
    return {"mean": float(np.mean(r)), "std": std, "n": int(len(r)), "within_spread": within}


def _mm(s: dict) -> str:
    if not np.isfinite(s["mean"]):
        return "inf"
    spread = f" ± {s['std'] * 1e3:.1f}" if np.isfinite(s["std"]) else ""  # one run: no spread
    return f"{s['mean'] * 1e3:.1f}{spread}"


def summary_table(summary: dict, labels: dict[str, tuple[str, ...]]) -> str:
    """Markdown: mean ± spread (mm) per row and column, each with its paired ratio to ours, and the
    paired ratio of the best baseline to ours per column (the issue's target: >= 1.6)."""
    runs = summary["runs"]
    seeds = sorted({r["seed"] for r in runs})
    draws = sorted({r["draw"] for r in runs})
    lines = [f"Table 7.1 protocol, task {summary['task']}: {len(runs)} runs (seeds {seeds} x draws {draws})"
             + (" (--quick: tiny training budgets, numbers meaningless)" if summary["quick"] else ""), "",
             "Symmetric closest-point distance in mm, mean ± sample standard deviation over the runs; "
             "[x] = paired ratio to (1) Multimodal (mean ± spread over the runs; * = 1 lies within the spread).", "",
             "| Method | n | " + " | ".join(k.replace("_", " ") for k in SCORE_KEYS) + " |",
             "|---|---|" + "---|" * len(SCORE_KEYS)]
    for name, row in summary["rows"].items():
        cells = []
        for k in SCORE_KEYS:
            c = _mm(row[k])
            ratio = row[k].get("ratio")
            if ratio and ratio["n"] and np.isfinite(ratio["mean"]):
                spread = f" ± {ratio['std']:.2f}" if np.isfinite(ratio["std"]) else ""
                c += f" [{ratio['mean']:.2f}x{spread}{' *' if ratio['within_spread'] and ratio['n'] > 1 else ''}]"
            cells.append(c)
        label = labels.get(name, (name,))[0]
        failed = f" (failed: {'; '.join(row['failed'])})" if row["failed"] else ""
        lines.append(f"| {label}{failed} | {row['n']} | " + " | ".join(cells) + " |")
    lines += ["", "Best baseline / ours, paired over the runs (target >= 1.6):", ""]
    for k, b in summary["best_baseline"].items():
        spread = f" ± {b['std']:.2f}" if np.isfinite(b["std"]) else " (one run: no spread)"
        lines.append(f"- {k.replace('_', ' ')}: {labels.get(b['row'], (b['row'],))[0]}, "
                     f"{b['mean']:.2f}x{spread} over {b['n']} runs")
    return "\n".join(lines) + "\n"


def run_grid(evaluate_one, seeds: list[int], draws: int, out: Path, labels: dict[str, tuple[str, ...]]) -> str:
    """``evaluate_one(seed, draw, folder)`` for every seed and draw 0..draws-1 into
    ``out/seed<S>-draw<D>``, then summary.json and summary.md over them in ``out``; returns the
    summary's markdown."""
    if not seeds or draws < 1:
        raise RunError(f"--seeds needs at least one seed and --draws at least 1 (got {seeds}, {draws})")
    folders = []
    for seed in seeds:
        for draw in range(draws):
            folder = out / f"seed{seed}-draw{draw}"
            evaluate_one(seed, draw, folder)
            folders.append(folder)
    return write_summary(out, folders, labels)


def write_summary(out: Path, folders: list[Path], labels: dict[str, tuple[str, ...]]) -> str:
    summary = summarize(folders)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    text = summary_table(summary, labels)
    (out / "summary.md").write_text(text)
    return text
