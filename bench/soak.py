"""Chaos soak: the simulated cell under the supervisor, a kill -9 of a random service every few
seconds, one CPU-hog process beside it, the cell's own recorder recording throughout.

Reports per kill the time until the killed service publishes again (every one of its registered
keys, or for services without keys its @health answering from the new process), the outage of
every key around the kill (from live arrivals), the recording's largest gap per key around the
kill beyond the key's nominal period, each restarted service's start-up (its "ready" log line),
stuck services (not back within --stuck-after), spurious brakes (the board's watchdog braking
while trajectories flow and no kill on the command path is being recovered, counted by the
world's simulated board) and the RSS of every service over time. Writes .bench/soak.json.

Each spurious brake carries the robot service's account of the command gap before it (how late its
thread woke, how long the tick took, how long it waited for a CPU) and whether the host stalled at
that moment: a real-time probe thread of the soak, above the cell's, records every wake-up over 8 ms
late with the hypervisor's steal time per CPU. A gap that ends within 50 ms of a probe stall is the
host's (on a virtual machine: its CPUs taken away), not the cell's.
Targets: every kill recovered within 3 s (p100), 0 stuck, a recording gap per kill <= 1 s on
every key, RSS growth <= 10 %, 0 spurious brakes.

On a host shared with other work, ``--autogroup-nice -10`` keeps that work from distorting the
figures: the soak, the cell (every service, spare and restarted process) and its hog share the
CPU as if they had the host to themselves. Linux schedules each session (``setsid``; every
service is one) as an autogroup, so ``nice`` does not reach across them; the soak moves
``/proc/<pid>/autogroup`` of each of its processes by that many nice values, once, and so every
process the supervisor starts later (root, or a negative value needs CAP_SYS_NICE). A shift, not a
value: the world's own boost over the services (``cpu_share_boost``) stays.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # runnable as a script from anywhere
sys.path.insert(0, str(ROOT / "bench"))  # its report module

from _host_probe import attribute_brakes, foreign_rt_threads, io_pressure, stall_probe  # noqa: E402
from _soak_report import (  # noqa: E402
    ready_after_start,
    recording_gaps,
    rss_growth,
    summarize,
    unplanned_exits,
)

from deploy.supervisor import query_json  # noqa: E402
from shared import keys  # noqa: E402
from shared.realtime import shift_autogroup  # noqa: E402
from shared.recording_files import recording_segments  # noqa: E402
from shared.runtime import open_client  # noqa: E402


def descendants(roots: list[int]) -> set[int]:
    """The processes below ``roots`` (and the roots), from /proc's parent links."""
    children: dict[int, list[int]] = defaultdict(list)
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])  # after "pid (comm)": state, ppid
        except (OSError, IndexError, ValueError):
            continue  # exited meanwhile
        children[ppid].append(int(stat.parent.name))
    seen, todo = set(), list(roots)
    while todo:
        pid = todo.pop()
        if pid not in seen:
            seen.add(pid)
            todo.extend(children.get(pid, []))
    return seen


def autogroup_id(pid: int) -> str | None:
    """A process's autogroup ("/autogroup-123"), shared by every process of its session."""
    try:
        return Path(f"/proc/{pid}/autogroup").read_text().split()[0]
    except (OSError, IndexError):
        return None


def shift_autogroups(pids: set[int], steps: int, done: set[str]) -> int:
    """Moves each autogroup of these processes ``steps`` nice values, once per autogroup (``done``:
    a service's child process shares its group), so a service that raised its own share (the world)
    stays ahead of the others; returns how many moved."""
    moved = 0
    for pid in pids:
        group = autogroup_id(pid)
        if group is not None and group not in done:
            done.add(group)
            moved += shift_autogroup(pid, steps) is not None
    return moved


def autogroup_keeper(roots: list[int], steps: int, stop: threading.Event, result: dict) -> None:
    """Boosts the soak's process tree every 0.5 s, so restarted services and new spares follow."""
    done: set[str] = set()
    while not stop.is_set():
        result["groups_set"] += shift_autogroups(descendants(roots), steps, done)
        stop.wait(0.5)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def private_deployment(src: Path, tmp: Path) -> tuple[Path, str]:
    """The deployment with its own router port, run dir, panel port and recordings folder, and no
    first-network training job (the panel would start one when the checkpoint is missing)."""
    text = src.read_text()
    router = f"tcp/127.0.0.1:{free_port()}"
    text = re.sub(r'router = "[^"]*"', f'router = "{router}"', text)
    text = re.sub(r'run_dir = "[^"]*"', f'run_dir = "{tmp}/run"', text)
    text = re.sub(r"port = 8080", f"port = {free_port()}", text)
    text = re.sub(r'directory = "[^"]*"', f'directory = "{tmp}/recordings"', text)
    text = re.sub(r'first_network = "[^"]*"', 'first_network = ""', text)  # no training job in the measurement
    out = tmp / "soak.toml"
    out.write_text(text)
    return out, router


class Monitor:
    """Arrival times (monotonic) of every key, and @health queries, over one client session."""

    def __init__(self, router: str, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while True:  # the supervisor's router takes a few seconds to listen on a busy host
            try:
                self.session = open_client(router)
                break
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        self.arrivals: dict[str, list[float]] = defaultdict(list)
        self._lock = threading.Lock()
        self._sub = self.session.declare_subscriber("xm/**", self._on)

    def _on(self, sample) -> None:
        with self._lock:
            self.arrivals[str(sample.key_expr)].append(time.monotonic())

    def first_after(self, key: str, t: float) -> float | None:
        with self._lock:
            times = self.arrivals.get(key, [])
            i = int(np.searchsorted(times, t, side="right"))
            return times[i] if i < len(times) else None

    def last_before(self, key: str, t: float) -> float | None:
        with self._lock:
            times = self.arrivals.get(key, [])
            i = int(np.searchsorted(times, t, side="right"))
            return times[i - 1] if i else None

    def health(self, selector: str, timeout: float = 1.0) -> list[dict]:
        return query_json(self.session, selector, timeout)

    def children(self) -> list[dict]:
        sup = self.health("xm/deploy/supervisor/@health")
        return sup[0]["children"] if sup else []

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


def keys_of(service: str, instance: str) -> list[str]:
    """Registered keys a service instance publishes (camhub publishes per camera, not per instance)."""
    mine = [s.key for s in keys.REGISTRY if s.service == service]
    own = [k for k in mine if k.split("/")[2:3] == [instance]]
    return own or mine


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def wait_up(monitor: Monitor, timeout: float, spares: bool = False) -> bool:
    """Every registered key publishing, and with ``spares`` every service's spare imported and prepared."""
    deadline = time.monotonic() + timeout
    wanted = {s.key for s in keys.REGISTRY}
    while time.monotonic() < deadline:
        now = time.monotonic()
        if all((t := monitor.last_before(k, now)) is not None and now - t < 2.0 for k in wanted) and (
                not spares or all(c.get("spare_ready") for c in monitor.children())):
            return True
        time.sleep(0.5)
    return False


def measure_kill(monitor: Monitor, child: dict, stuck_after: float) -> dict:
    """kill -9 one child, then wait until it is publishing again; the kill's record."""
    service, instance, pid = child["service"], child["instance"], child["pid"]
    own = keys_of(service, instance)
    t_kill = time.monotonic()
    wall_kill = time.time()
    os.kill(pid, signal.SIGKILL)
    deadline = t_kill + stuck_after
    back: float | None = None
    new_pid = None
    while time.monotonic() < deadline:
        if own:
            firsts = [monitor.first_after(k, t_kill + 0.02) for k in own]
            if all(f is not None for f in firsts):
                back = max(firsts)
        if back is None or new_pid is None:
            mine = [c for c in monitor.children() if (c["service"], c["instance"]) == (service, instance)]
            new_pid = mine[0]["pid"] if mine and mine[0]["pid"] not in (None, pid) else None
            if not own and new_pid is not None:
                h = monitor.health(f"xm/{service}/{instance}/@health", 0.5)
                if h and h[0].get("pid") == new_pid and h[0].get("status") not in ("starting",):
                    back = time.monotonic()
        if back is not None:
            break
        time.sleep(0.02)
    return {"service": f"{service}/{instance}", "old_pid": pid, "new_pid": new_pid, "t_kill": wall_kill,
            "t_kill_mono": t_kill, "recovered_s": None if back is None else round(back - t_kill, 3),
            "stuck": back is None, "keys": own}


def outages(monitor: Monitor, t_kill: float, until: float) -> dict[str, float]:
    """Per key: the longest silence between the last arrival before the kill and ``until``."""
    out = {}
    for spec in keys.REGISTRY:
        with monitor._lock:
            times = np.asarray(monitor.arrivals.get(spec.key, []))
        window = times[(times >= t_kill - 1.0) & (times <= until)]
        last = monitor.last_before(spec.key, t_kill - 1.0)
        edges = np.concatenate([[last] if last is not None else [], window, [until]])
        out[spec.key] = round(float(np.diff(edges).max()), 3) if len(edges) > 1 else None
    return out


def recorder_cmd(monitor: Monitor, cmd: str, req: dict) -> dict:
    """A command to the deployment's recorder (``xm/recorder/main/@cmd/...``); {} when none answers."""
    for _ in range(20):  # the recorder may be between a kill and its restart
        replies = [r.ok for r in monitor.session.get(f"xm/recorder/main/@cmd/{cmd}", payload=json.dumps(req),
                                                     timeout=5.0) if r.ok is not None]
        if replies:
            return json.loads(replies[0].payload.to_bytes())
        time.sleep(0.5)
    return {}


def sample_rss(monitor: Monitor, series: dict, t0: float) -> None:
    now = time.monotonic()
    cell = {p for c in monitor.children() for p in (c.get("pid"), c.get("spare_pid")) if p}
    series["_loadavg"].append({"t": round(now - t0, 1), "loadavg_1m": round(os.getloadavg()[0], 2),
                               "io_pressure_10s": io_pressure(), "foreign_rt_threads": foreign_rt_threads(cell)})
    for c in monitor.children():
        if c.get("pid"):
            mb = rss_mb(c["pid"])
            if mb is not None:
                series[f"{c['service']}/{c['instance']}"].append(
                    {"t": round(now - t0, 1), "pid": c["pid"], "age_s": c["uptime_s"], "rss_mb": round(mb, 1)})


def brake_sampler(monitor: Monitor, robot: str, stop: threading.Event, result: dict) -> None:
    """Counts the board's watchdog brakes (the world's counter, exact) and sorts each one by the
    sequence of the command before it: a kill of a service on the command path being recovered
    (trajopt, robot, world, or their inputs), or no trajectory in the last 0.5 s: expected; else
    spurious, and of those, the ones after a gap over 9 ms in the robot service's own command
    stream (its process stalled: ``after_host_gap``) and the others (the pty or the world starved
    the board's watchdog). Also samples the watchdog state at ~5 Hz: braking while commanded."""
    key = "xm/trajopt/main/trajectory"
    prev_state, prev_board, last_poll = "ok", None, time.monotonic()
    while not stop.is_set():
        h = monitor.health(f"xm/robot/{robot}/@health", 0.5)
        now = time.monotonic()
        last = monitor.last_before(key, now)
        commanded = last is not None and now - last < 0.5
        quiet = result["recovering"] or now - result["recovered_at"] < now - last_poll + 0.5
        if h:
            state = h[0].get("watchdog", "unknown")
            result["samples"] += 1
            # host gaps over 10 ms that a plan carried the board through, per robot process
            stream = h[0].get("command_stream", {})
            result["gaps_bridged_by_pid"][str(h[0].get("pid"))] = [stream.get("gaps_bridged", 0),
                                                                   stream.get("max_gap_ms", 0.0)]
            if state == "braking" and commanded and not quiet:
                result["braking_samples_while_commanded"] += 1
                if prev_state != "braking":
                    result["braking_seen_while_commanded"] += 1
            prev_state = state
        w = monitor.health("xm/world/sim/@health", 0.5)
        board = (w[0].get("devices") or {}).get("robot") if w else None
        if board is not None and h:
            pid, count = w[0].get("pid"), board.get("watchdog_brakes", 0)
            if prev_board is not None and prev_board[0] == pid and count > prev_board[1]:
                new = board.get("brakes_after", [])[-(count - prev_board[1]):]
                host_gaps = set(h[0].get("command_stream", {}).get("gaps_after", []))
                parts = {g.get("after"): g for g in h[0].get("command_stream", {}).get("gap_parts", [])}
                for seq in new:
                    if quiet or not commanded:
                        result["board_brakes_expected"] += 1
                    else:
                        result["spurious_brakes"] += 1
                        kind = "after_host_gap" if seq in host_gaps else "board_starved"
                        result["spurious_by_cause"][kind] += 1
                        result["events"].append({"t": round(now - result["t0"], 1), "after_sequence": seq,
                                                 "cause": kind, "host_gap": parts.get(seq)})
            prev_board = (pid, count)
        last_poll = now
        stop.wait(0.2)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bench/soak.py", description=__doc__.split("\n\n")[0])
    add = parser.add_argument
    add("--minutes", type=float, default=60.0, help="soak length (default %(default)s)")
    add("--kill-every", type=float, default=60.0, metavar="S", help="seconds between kills (default %(default)s)")
    add("--hog", action=argparse.BooleanOptionalAction, default=True,
        help="run one CPU-bound process beside the cell (default: on)")
    add("--standby", action=argparse.BooleanOptionalAction, default=True,
        help="an imported spare per service takes over, as in `xm up` (default: on; --no-standby: cold restarts)")
    add("--deployment", default=str(ROOT / "deploy/sim.toml"))
    add("--seed", type=int, default=0, help="which services are killed, in which order")
    add("--each", action="store_true", help="kill every service once, in the deployment's order, instead of at "
        "random (a per-service recovery table: with --no-standby, cold restarts)")
    add("--only", action="append", metavar="SERVICE", help="kill only this service (repeat for more; e.g. "
        "--only recorder)")
    add("--stuck-after", type=float, default=30.0, metavar="S",
        help="a service not publishing again this long after its kill is stuck")
    add("--autogroup-nice", type=int, metavar="N", help="move the autogroups of the soak, the cell and its hog by "
        "this many nice values (e.g. -10 on a host shared with other work; Linux, see above)")
    add("--out", default=str(ROOT / ".bench/soak.json"))
    args = parser.parse_args(argv)

    # SIGTERM (kill, a CI timeout) ends the soak as Ctrl-C does: the cell and the hog are stopped below.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    tmp = Path(tempfile.mkdtemp(prefix="xm-soak-"))
    deployment, router = private_deployment(Path(args.deployment), tmp)
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    up_log = (tmp / "up.log").open("w")
    up = subprocess.Popen([sys.executable, "-m", "shared.cli", "up", str(deployment), "--quiet",
                           "--standby" if args.standby else "--no-standby"], cwd=ROOT,
                          stdout=up_log, stderr=subprocess.STDOUT, start_new_session=True, env=env)
    procs = [up]
    report: dict = {"deployment": str(args.deployment), "minutes": args.minutes, "kill_every_s": args.kill_every,
                    "hog": args.hog, "standby": args.standby, "only": args.only, "cpus": os.cpu_count(),
                    "commit": git_commit(), "loadavg_start": os.getloadavg(), "kills": []}
    monitor = None
    boost_stop = threading.Event()
    if args.autogroup_nice is not None:
        report["autogroup_nice"] = {"shift": args.autogroup_nice, "groups_set": 0}
        threading.Thread(target=autogroup_keeper, args=([os.getpid()], args.autogroup_nice, boost_stop,
                                                        report["autogroup_nice"]), daemon=True).start()
    try:
        time.sleep(1.0)
        monitor = Monitor(router)
        if not wait_up(monitor, 300, spares=args.standby):
            print(f"the cell did not come up; see {tmp}/up.log", file=sys.stderr)
            return 1
        if args.hog:
            procs.append(subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True))
        # The cell's own recorder records (segments, resumed after its own kill), so killing it counts.
        mcap = tmp / "recordings" / "soak.mcap"
        started = recorder_cmd(monitor, "start", {"path": str(mcap)})
        if not started.get("ok"):
            print(f"the recorder did not start: {started}", file=sys.stderr)
            return 1
        robot = next((c["instance"] for c in monitor.children() if c["service"] == "robot"), "workcell")
        t0 = time.monotonic()
        brakes = {"t0": t0, "samples": 0, "braking_samples_while_commanded": 0, "braking_seen_while_commanded": 0,
                  "spurious_brakes": 0, "spurious_by_cause": {"after_host_gap": 0, "board_starved": 0},
                  "gaps_bridged_by_pid": {},
                  "board_brakes_expected": 0, "events": [], "recovering": False, "recovered_at": -np.inf}
        stop = threading.Event()
        sampler = threading.Thread(target=brake_sampler, args=(monitor, robot, stop, brakes), daemon=True)
        sampler.start()
        stalls: list = []
        threading.Thread(target=stall_probe, args=(stop, t0, stalls), daemon=True).start()
        rss: dict = defaultdict(list)
        rng = random.Random(args.seed)
        end = t0 + args.minutes * 60
        next_kill = t0 + min(args.kill_every, 20.0)
        next_rss = t0
        while time.monotonic() < end:
            now = time.monotonic()
            if now >= next_rss:
                sample_rss(monitor, rss, t0)
                next_rss = now + 10.0
            if now >= next_kill and now + 15 < end:
                children = [c for c in monitor.children()
                            if c.get("pid") and (not args.only or c["service"] in args.only)]
                if args.each:
                    children = children[len(report["kills"]):len(report["kills"]) + 1]
                if children:
                    child = children[0] if args.each else rng.choice(children)
                    brakes["recovering"] = child["service"] in ("world", "robot", "trajopt", "policy", "recon",
                                                                "camhub")
                    kill = measure_kill(monitor, child, args.stuck_after)
                    time.sleep(3.0)  # let downstream services settle before judging brakes again
                    if brakes["recovering"]:
                        brakes["recovered_at"] = time.monotonic()
                    brakes["recovering"] = False
                    kill["outage_s"] = outages(monitor, kill["t_kill_mono"], time.monotonic())
                    kill["t"] = round(kill.pop("t_kill_mono") - t0, 1)
                    service, instance = kill["service"].split("/")
                    kill["ready_after_start_s"] = ready_after_start(tmp / "run" / "logs" / f"{service}-{instance}.log")
                    if service == "world":  # the new world's own account: its clock's longest gap, CPU wait
                        h = monitor.health(f"xm/{service}/{instance}/@health", 1.0)
                        kill["world_clock_gap"] = h[0].get("clock_gap") if h else None
                    report["kills"].append(kill)
                    save(Path(args.out), {**report, "partial": True, "rss": dict(rss)})  # kept if the run dies
                    print(f"[{kill['t']:7.1f} s] kill -9 {kill['service']}: "
                          f"{'STUCK' if kill['stuck'] else str(kill['recovered_s']) + ' s'}", flush=True)
                next_kill = now + args.kill_every
            time.sleep(0.2)
        stop.set()
        sampler.join(2)
        report["loadavg"] = rss.pop("_loadavg")
        for k in ("t0", "recovering", "recovered_at"):
            brakes.pop(k)
        report["brakes"] = brakes
        report["host_stalls"] = {"probe_late_over_8ms": stalls, "count": len(stalls),
                                 "with_steal": sum(any(s.get("steal_ms_per_cpu", [])) for s in stalls)}
        brakes["spurious_not_at_host_stall"] = attribute_brakes(brakes["events"], stalls)
        report["rss"] = dict(rss)
        report["rss_growth"] = rss_growth(rss)
        report["unplanned_exits"] = unplanned_exits(tmp / "up.log", report["kills"])
        report["final_health"] = {f"{h['service']}/{h['instance']}": {
            k: h.get(k) for k in ("status", "message", "errors", "rejected", "dropped", "clock_jumps")}
            for h in monitor.health("xm/**/@health", 2.0)}
        report["loadavg_end"] = os.getloadavg()
        try:  # an hour of kills is worth keeping even if the recording cannot be analysed
            stopped = recorder_cmd(monitor, "stop", {})
            gaps = recording_gaps(mcap, report["kills"])
            for kill, g, b in zip(report["kills"], gaps["per_kill"], gaps["beyond_normal"], strict=True):
                kill["recording_gap_s"] = g
                kill["recording_gap_beyond_normal_s"] = b
            segments = recording_segments(mcap)
            report["recording"] = {"messages": gaps["messages"], "cut": gaps["cut"], "segments": len(segments),
                                   "bytes": sum(p.stat().st_size for p in segments), "stopped": stopped.get("ok"),
                                   "normal_spacing_s": gaps["normal_spacing_s"]}
        except Exception as exc:
            report["recording_error"] = repr(exc)
            print(f"recording not analysed: {exc!r} (it is in {tmp}/recordings)", file=sys.stderr)
        report["summary"] = summarize(report)
    finally:
        boost_stop.set()
        for p in reversed(procs):
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGINT if p is up else signal.SIGKILL)
                except ProcessLookupError:
                    pass
        try:
            up.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(up.pid, signal.SIGKILL)
        up_log.close()
        if monitor is not None:
            monitor.close()
    save(Path(args.out), report)
    print(json.dumps(report.get("summary"), indent=1))
    print(f"wrote {args.out} (logs in {tmp})")
    return 0


def git_commit() -> str | None:
    """The checkout's commit, with "+dirty" when its tracked files differ from it."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "diff", "--quiet", "HEAD"], cwd=ROOT).returncode != 0
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("+dirty" if dirty else "")


def save(out: Path, report: dict) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(report, indent=1))
    os.replace(tmp, out)


if __name__ == "__main__":
    sys.exit(main())
