"""The soak's report (bench/soak.py): recording gaps per kill and key, unplanned exits and spare
readiness from the supervisor's log, RSS growth per process, and the summary against the targets.
Pure reads of what the soak collected; no processes started."""

from __future__ import annotations

import re
import signal
from collections import defaultdict
from pathlib import Path

import numpy as np

from shared import keys

RECOVERY_TARGET_S = 3.0
GAP_TARGET_S = 1.0
RSS_GROWTH_TARGET = 0.10
RSS_WARMUP_S = 30.0  # a process's RSS is compared from this age on (imports, caches, first frames)
WINDOW_S = 10.0  # the recording is searched for gaps from 1 s before a kill to this long after


def ready_after_start(log: Path) -> float | None:
    """The newest "ready" of a service's log: its start-up before it can publish (a fresh process:
    interpreter, imports, connecting, building the service; a spare: connecting and building)."""
    try:
        lines = log.read_text(errors="replace").splitlines()[-400:]
    except OSError:
        return None
    for line in reversed(lines):
        for field in ("since_process_start_s=", "since_taken_over_s="):  # a fresh process, or a spare
            if " ready " in line and field in line:
                return float(line.rsplit(field, 1)[1].split()[0])
    return None


def unplanned_exits(up_log: Path, kills: list[dict]) -> list[dict]:
    """Exits the soak did not cause, from the supervisor's log: every exit other than SIGKILL, and
    SIGKILLs of a service beyond the soak's kills of it (a crash, an abort, the OOM killer)."""
    killed = defaultdict(int)
    for k in kills:
        killed[k["service"]] += 1
    out = []
    try:
        lines = up_log.read_text(errors="replace").splitlines()
    except OSError:
        return out
    for line in lines:
        m = re.match(r"(\S+) WARNING supervisor: (\S+) exited code=(-?\d+) ran_s=(\S+)", line)
        if not m:
            continue
        at, name, code, ran = m.group(1), m.group(2), int(m.group(3)), float(m.group(4))
        if code == -signal.SIGKILL and killed[name] > 0:
            killed[name] -= 1
            continue
        out.append({"at": at, "service": name, "code": code, "ran_s": ran})
    return out


def recording_gaps(path: Path, kills: list[dict]) -> dict:
    """Per kill and key: what the kill cost the recording. The largest interval between recorded
    messages (log time) from 1 s before the kill to WINDOW_S after it, less the key's nominal
    period (``per_kill``: the target's measure), and less the key's normal spacing
    (``beyond_normal``: the 99th percentile of its intervals away from every kill when that is
    longer than the period: a loaded host stalls publishers without any kill, and the world's
    1 Hz sim-time session key is further apart in wall time when the world runs late). Killing the
    recorder shows on every key; killing a key's only publisher shows on its keys."""
    from services.recorder.writer import read_messages

    times: dict[str, list[float]] = defaultdict(list)
    cut: list[str] = []
    for m in read_messages(path, cut=cut):
        times[m.key].append(m.log_time * 1e-9)
    arrays = {k: np.sort(np.asarray(v)) for k, v in times.items()}
    windows = [(k["t_kill"] - 1.0, k["t_kill"] + WINDOW_S) for k in kills]
    normal: dict[str, float] = {}
    for spec in keys.REGISTRY:
        ts = arrays.get(spec.key, np.zeros(0))
        dt, mid = np.diff(ts), (ts[1:] + ts[:-1]) / 2 if len(ts) > 1 else np.zeros(0)
        away = np.ones(len(dt), bool)
        for a, b in windows:
            away &= (mid < a) | (mid > b)
        p99 = float(np.percentile(dt[away], 99)) if away.sum() >= 10 else 0.0
        normal[spec.key] = round(max(1.0 / spec.rate_hz, p99), 3)
    per_kill, beyond_normal = [], []
    for a, b in windows:
        gaps, beyond = {}, {}
        for spec in keys.REGISTRY:
            ts = arrays.get(spec.key, np.zeros(0))
            inside = ts[(ts >= a) & (ts <= b)]
            longest = float(np.diff(np.concatenate([[a], inside, [b]])).max())
            gaps[spec.key] = round(max(0.0, longest - 1.0 / spec.rate_hz), 3)
            beyond[spec.key] = round(max(0.0, longest - normal[spec.key]), 3)
        per_kill.append(gaps)
        beyond_normal.append(beyond)
    return {"per_kill": per_kill, "beyond_normal": beyond_normal, "normal_spacing_s": normal,
            "messages": {k: len(v) for k, v in arrays.items()}, "cut": cut}


def rss_growth(series: dict) -> dict:
    """Per service: the largest RSS growth of one process from its RSS_WARMUP_S sample to its last."""
    out = {}
    for name, samples in series.items():
        if name.startswith("_"):
            continue
        worst = None
        for pid in {s["pid"] for s in samples}:
            mine = [s for s in samples if s["pid"] == pid and s["age_s"] >= RSS_WARMUP_S]
            if len(mine) >= 2 and mine[-1]["age_s"] - mine[0]["age_s"] >= 60:
                g = mine[-1]["rss_mb"] / mine[0]["rss_mb"] - 1
                worst = g if worst is None else max(worst, g)
        out[name] = None if worst is None else round(worst, 4)
    return out


def summarize(report: dict) -> dict:
    kills = report["kills"]
    rec = [k["recovered_s"] for k in kills if k["recovered_s"] is not None]
    gap = [max(v for v in k.get("recording_gap_s", {}).values()) for k in kills if k.get("recording_gap_s")]
    growth = [g for g in report["rss_growth"].values() if g is not None]
    by_service: dict[str, list] = defaultdict(list)
    ready: dict[str, list] = defaultdict(list)
    for k in kills:
        by_service[k["service"]].append(k["recovered_s"])
        ready[k["service"]].append(k.get("ready_after_start_s"))
    # Gaps on keys of services that were not killed: what a kill costs the rest of the cell.
    others = [max((v for key, v in k["recording_gap_s"].items() if key not in k["keys"]), default=0.0)
              for k in kills if k.get("recording_gap_s")]
    return {
        "kills": len(kills),
        "recovered_p50_s": float(np.median(rec)) if rec else None,
        "recovered_p100_s": max(rec) if rec else None,
        "recovered_within_target": sum(r <= RECOVERY_TARGET_S for r in rec),
        "recovery_by_service_s": dict(by_service),
        "ready_after_process_start_s": dict(ready),
        "stuck": sum(k["stuck"] for k in kills),
        "unplanned_exits": len(report.get("unplanned_exits", [])),
        "recording_gap_max_per_kill_s": gap,
        "recording_gap_over_target": sum(g > GAP_TARGET_S for g in gap),
        "recording_gap_max_on_other_services_keys_s": others,
        "recording_gap_beyond_normal_max_per_kill_s": [max(k["recording_gap_beyond_normal_s"].values())
                                                       for k in kills if k.get("recording_gap_beyond_normal_s")],
        "recording_gap_max_by_key_s": {key: max(k["recording_gap_s"][key] for k in kills if k.get("recording_gap_s"))
                                       for key in (kills[0].get("recording_gap_s") or {})} if kills else {},
        "loadavg_1m_median": float(np.median([x["loadavg_1m"] for x in report.get("loadavg", [])]))
        if report.get("loadavg") else None,
        "rss_growth_max": max(growth) if growth else None,
        "spurious_brakes": report["brakes"]["spurious_brakes"],
        "spurious_brakes_by_cause": report["brakes"]["spurious_by_cause"],
        # a brake within 1 s of a late wake-up of the soak's own real-time probe: the host stalled
        "spurious_brakes_not_at_host_stall": report["brakes"].get("spurious_not_at_host_stall"),
        "host_stalls_over_8ms": (report.get("host_stalls") or {}).get("count"),
        "host_stalls_with_hypervisor_steal": (report.get("host_stalls") or {}).get("with_steal"),
        "board_brakes_expected": report["brakes"]["board_brakes_expected"],
        # gaps over 10 ms in the robot's command stream that its plans carried the board through
        "host_gaps_bridged_by_plans": sum(v[0] for v in report["brakes"].get("gaps_bridged_by_pid", {}).values()),
        "host_gap_max_ms": max((v[1] for v in report["brakes"].get("gaps_bridged_by_pid", {}).values()), default=None),
        "targets": {"recovered_p100_s": RECOVERY_TARGET_S, "stuck": 0, "recording_gap_s": GAP_TARGET_S,
                    "rss_growth": RSS_GROWTH_TARGET, "spurious_brakes": 0},
    }
