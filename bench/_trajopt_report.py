"""Summaries and the markdown table of bench/trajopt.py (a helper module: `make bench` runs only the
scripts without a leading underscore)."""

from __future__ import annotations

import numpy as np


def summarize(rec: dict) -> dict:
    if "error" in rec:
        return rec
    ms = lambda xs, q: 1e3 * float(np.percentile(xs, q))  # noqa: E731
    checks = [c for c in rec["checks"] if c is not None]
    failures = [s for ok, s in zip(rec["ok"], rec["status"], strict=True) if not ok]
    res = {"label": rec["label"], "kind": rec["kind"],
           "p50_ms": ms(rec["wall"], 50), "p95_ms": ms(rec["wall"], 95),
           "cpu_p50_ms": ms(rec["cpu"], 50), "cpu_p95_ms": ms(rec["cpu"], 95),
           "mean_iterations": float(np.mean(rec["its"])), "max_iterations": int(np.max(rec["its"])),
           "solves": len(rec["wall"]), "failed": len(failures),
           "failure_example": failures[0][:200] if failures else "",
           "build_s": rec["build_s"], "first_solve_s": rec["first_solve_s"], "compile_s": rec["compile_s"]}
    if checks:
        worst = max(checks, key=lambda c: c["violation"])
        res |= {"max_violation": worst["violation"],
                "worst_constraint": worst["what"] if worst["violation"] > 0 else "",
                "violations_over_1e-3": sum(c["violation"] > 1e-3 for c in checks),
                "max_tracking_error_mm": 1e3 * max(c["err"] for c in checks),
                "median_tracking_error_mm": 1e3 * float(np.median([c["err"] for c in checks])),
                "min_arm_distance_mm": 1e3 * min(c["dmin"] for c in checks),
                "_costs": [c["cost"] if c is not None else np.nan for c in rec["checks"]]}
    return res


def table(res: dict, problem: dict) -> str:
    """The comparison as a markdown table (what docs/trajopt.md shows)."""
    head = ("| solver | p50 ms | p95 ms | CPU p50 / p95 ms | iterations mean (max) | failed | max violation | "
            "goal error median / max mm | min distance mm | cost vs IPOPT | speed vs Opti+IPOPT p50 / p95 |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in res.values():
        if "p50_ms" not in r:
            lines.append(f"| {r['label']} | {r['error']} |" + " |" * 9)
            continue
        viol = f"{r['max_violation']:.1e}" if "max_violation" in r else "-"
        err = (f"{r['median_tracking_error_mm']:.2f} / {r['max_tracking_error_mm']:.1f}"
               if "max_tracking_error_mm" in r else "-")
        dist = f"{r['min_arm_distance_mm']:.2f}" if "min_arm_distance_mm" in r else "-"
        cost = r.get("median_cost_vs_opti_ipopt")
        compile_s = f" (compile {r['compile_s']:.0f} s)" if r.get("compile_s") else ""
        lines.append(f"| {r['label']}{compile_s} | {r['p50_ms']:.1f} | {r['p95_ms']:.1f} | "
                     f"{r['cpu_p50_ms']:.1f} / {r['cpu_p95_ms']:.1f} | {r['mean_iterations']:.1f} "
                     f"({r['max_iterations']}) | {r['failed']}/{r['solves']} | {viol} | {err} | {dist} | "
                     f"{'-' if cost is None else f'{cost:.3f}'} | "
                     f"{r['ratio_p50_vs_opti_ipopt']:.1f}x / {r['ratio_p95_vs_opti_ipopt']:.1f}x |")
    lines.append(f"\n{problem['problems'] - problem['warmup']} warm solves each (after {problem['warmup']}), "
                 f"1-min load average {problem['load_avg_1min']:.2f} -> {problem['load_avg_1min_end']:.2f} "
                 f"on {problem['cpu_count']} cores, CasADi {problem['casadi']}, {problem['measured']}.")
    return "\n".join(lines)
