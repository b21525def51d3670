"""The supervisor behind ``xm up``: Zenoh router, one process per service, logs, restarts.

Every service instance of the deployment (a ``services/<name>`` package declaring its ports) runs
as ``python -m services.<name>``; its output is
prefixed and collected (console + ``<run_dir>/logs/<name>-<instance>.log``). A process that
dies is restarted with exponential backoff; liveliness tokens tell who is up. Each child is
"starting" (first start, no token yet), "restarting" (dead, waiting out its backoff),
"recovering" (restarted, no token yet) or "ok" (``xm status``). Unless ``--no-standby``, every child
has a spare: a process of the same service that has done its imports and waits
(``--standby``); when the child dies the spare takes over at once, and a new spare is started a
few seconds later, off the recovery's critical path. Ctrl-C stops everything: SIGTERM, a grace
period, then SIGKILL.
"""

from __future__ import annotations

import argparse
import asyncio
import importlib.util
import json
import os
import signal
import sys
import time
import webbrowser
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from deploy.certs import check_cert
from deploy.hosts import HostError, load_hosts, router_config
from shared.config import ConfigError, Deployment, load_deployment
from shared.realtime import autogroup_nice, can_lower_nice, shift_autogroup
from shared.runtime import EndpointError, Node, open_client, open_router
from shared.runtime.logs import fields, setup_logging
from shared.runtime.service import STANDBY_READY
from shared.wiring import bind, edges, start_order

BACKOFF_START_S = 0.5
BACKOFF_MAX_S = 20.0
HEALTHY_AFTER_S = 30.0  # a run this long resets the backoff
STOP_GRACE_S = 5.0
SPARE_DELAY_S = 5.0  # a new spare starts this long after the last was taken: its imports would slow the recovery
# A spare starts with its autogroup this many nice values up, so its start-up (seconds of imports,
# a renderer, a network) takes only CPU the cell leaves while it recovers from the kill; after
# SPARE_QUIET_S it is moved back (on a loaded host it would not be ready for the next kill), or
# as it hands over. Only where the supervisor may lower nice values (CAP_SYS_NICE).
SPARE_NICE_SHIFT = 15
SPARE_QUIET_S = 20.0


def backoff_delay(consecutive_failures: int) -> float:
    """0 for the first exit after a healthy run (a crash or kill: back at once), then doubling."""
    if consecutive_failures <= 1:
        return 0.0
    return min(BACKOFF_MAX_S, BACKOFF_START_S * 2 ** (consecutive_failures - 2))


@dataclass
class Child:
    service: str
    instance: str
    proc: asyncio.subprocess.Process | None = None
    started_at: float = 0.0
    restarts: int = 0
    failures: int = 0
    last_exit: int | None = None
    alive: bool = False
    log_tasks: list[asyncio.Task] = field(default_factory=list)
    spare: asyncio.subprocess.Process | None = None  # imported, waiting on stdin (--standby)
    spare_log_tasks: list[asyncio.Task] = field(default_factory=list)
    spare_ready_pid: int | None = None  # the spare that said it finished importing and preparing
    spare_shift: int = 0  # nice values the spare's autogroup was moved up while it waits

    @property
    def name(self) -> str:
        return f"{self.service}/{self.instance}"

    @property
    def state(self) -> str:
        if self.proc is None or self.proc.returncode is not None:
            return "restarting"
        if not self.alive:
            return "recovering" if self.restarts else "starting"
        return "ok"


class Supervisor:
    def __init__(self, deployment: Deployment, only: list[str] | None = None, quiet: bool = False,
                 standby: bool = False, host: str | None = None) -> None:
        self.deployment = deployment
        self.quiet = quiet
        self.standby = standby
        self._spare_tasks: set[asyncio.Task] = set()
        self._spare_nice = can_lower_nice()  # spares wait at a small CPU share only where it can be given back
        wanted = start_order(deployment)  # the deployment's order; services hosting devices (world) first
        self.router_config: dict | None = None
        if host is not None:  # one host of a multi-host deployment: its services, its router's TLS links and ACL
            hosts = load_hosts(deployment)
            mine = set(hosts.host(host).services)
            wanted = [w for w in wanted if w in mine]
            problem = check_cert(hosts.tls_dir / f"{host}.pem", hosts.tls_dir / "ca.pem")
            if problem:  # zenoh's own TLS error would not say which file or why
                raise ConfigError(f"host {host}: {problem}")
            self.router_config = router_config(deployment, hosts, host)
        if only:
            unknown = sorted(set(only) - {s for s, _ in wanted})
            if unknown:
                have = ", ".join(sorted({s for s, _ in wanted}))
                raise ConfigError(f"--only: unknown service(s) {', '.join(unknown)} (this deployment has: {have})")
            wanted = [(s, i) for s, i in wanted if s in only]
        for svc, inst in wanted:
            if importlib.util.find_spec(f"services.{svc}.__main__") is None:
                raise ConfigError(f"service {svc!r} has no services/{svc}/__main__.py in this build")
            bind(deployment, svc, inst)  # a bad input remap stops here, not in a restart loop
        self.children = [Child(s, i) for s, i in wanted]
        self.log_dir = deployment.run_dir / "logs"
        self.log = setup_logging("supervisor")
        self._stopping = False
        for problem in edges(deployment)[1]:  # `xm graph` shows the whole dataflow
            self.log.warning(f"wiring: {problem}")

    async def run(self, stop: asyncio.Event, open_browser: bool = False) -> None:
        self.deployment.run_dir.mkdir(parents=True, exist_ok=True)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        router = open_router(self.deployment.router, self.router_config)
        node = Node("deploy", "supervisor", router, "wall", self.log)
        node.health_extra = self.children_report
        node.set_status("ok")
        router.liveliness().declare_subscriber("xm/*/*/@alive", self._on_alive, history=True)
        self.log.info("router listening", extra=fields(endpoint=self.deployment.router,
                                                      deployment=str(self.deployment.path)))
        watchers = [asyncio.ensure_future(self._keep_running(child)) for child in self.children]
        panel = self.deployment.services.get("panel", {})
        if panel:
            port = next(iter(panel.values())).get("port", 8080)
            url = f"http://127.0.0.1:{port}"
            self.log.info(f"dashboard: {url}")
            if open_browser and (os.environ.get("DISPLAY") or sys.platform == "darwin"):
                asyncio.get_running_loop().call_later(3.0, webbrowser.open, url)
        try:
            await stop.wait()
        finally:
            self._stopping = True
            self.log.info("stopping all services")
            for task in self._spare_tasks:
                task.cancel()
            await asyncio.gather(*(self._stop_child(c) for c in self.children))
            for w in watchers:
                w.cancel()
            await asyncio.gather(*watchers, return_exceptions=True)
            await node.close()
            router.close()
            self.log.info("stopped")

    def _on_alive(self, sample) -> None:  # Zenoh thread: only flips a flag
        parts = str(sample.key_expr).split("/")
        for child in self.children:
            if parts[1:3] == [child.service, child.instance]:
                child.alive = sample.kind == zenoh.SampleKind.PUT

    async def _keep_running(self, child: Child) -> None:
        while not self._stopping:
            await self._start_child(child)
            code = await child.proc.wait()
            for task in child.log_tasks:
                await asyncio.gather(task, return_exceptions=True)
            child.last_exit = code
            child.alive = False
            if self._stopping:
                return
            ran = time.monotonic() - child.started_at
            child.failures = 1 if ran > HEALTHY_AFTER_S else child.failures + 1
            delay = backoff_delay(child.failures)
            self.log.warning(f"{child.name} exited", extra=fields(code=code, ran_s=round(ran, 1),
                                                                   restart_in_s=delay))
            await asyncio.sleep(delay)
            child.restarts += 1

    async def _start_child(self, child: Child) -> None:
        spare = child.spare
        if spare is not None and spare.returncode is None:
            self._spare_full_share(child, spare)  # its full CPU share before it starts working
            child.spare, child.proc, child.log_tasks = None, spare, child.spare_log_tasks
            try:
                spare.stdin.write(b"go\n")
                await spare.stdin.drain()
                self.log.info(f"started {child.name} from its spare", extra=fields(pid=spare.pid))
            except (BrokenPipeError, ConnectionResetError):  # the spare died meanwhile: its exit is handled
                pass
        else:
            child.proc, child.log_tasks = await self._spawn(child, spare=False)
            self.log.info(f"started {child.name}", extra=fields(pid=child.proc.pid))
        child.started_at = time.monotonic()
        if self.standby and not self._stopping:
            task = asyncio.ensure_future(self._spare_later(child))
            self._spare_tasks.add(task)
            task.add_done_callback(self._spare_tasks.discard)

    async def _spawn(self, child: Child, spare: bool) -> tuple[asyncio.subprocess.Process, list[asyncio.Task]]:
        cmd = [sys.executable, "-m", f"services.{child.service}",
               "--deployment", str(self.deployment.path), "--instance", child.instance]
        # PYTHONFAULTHANDLER: a native crash (SIGSEGV, SIGABRT from a corrupted heap) leaves every
        # thread's Python stack in the service's log.
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONFAULTHANDLER": "1"}
        # Two malloc arenas, not 8 per core: Zenoh's threads otherwise each grow an arena that keeps
        # freed payload memory (the recorder at rig rates: 8 MB less RSS, and it stops creeping).
        env.setdefault("MALLOC_ARENA_MAX", "2")
        root = str(Path(__file__).resolve().parent.parent)
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        proc = await asyncio.create_subprocess_exec(
            *cmd, *(["--standby"] if spare else []), stdin=asyncio.subprocess.PIPE if spare else None,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT, env=env, start_new_session=True)
        logfile = (self.log_dir / f"{child.service}-{child.instance}.log").open("a")
        return proc, [asyncio.ensure_future(self._pump(child, proc.stdout, logfile, proc.pid if spare else None))]

    async def _spare_later(self, child: Child) -> None:
        await asyncio.sleep(SPARE_DELAY_S)
        if self._stopping or (child.spare is not None and child.spare.returncode is None):
            return
        child.spare, child.spare_log_tasks = await self._spawn(child, spare=True)
        child.spare_shift = 0
        before = autogroup_nice(child.spare.pid)
        if self._spare_nice and before is not None:
            after = shift_autogroup(child.spare.pid, SPARE_NICE_SHIFT)
            child.spare_shift = 0 if after is None else after - before
            asyncio.get_running_loop().call_later(SPARE_QUIET_S, self._spare_full_share, child, child.spare)

    @staticmethod
    def _spare_full_share(child: Child, spare: asyncio.subprocess.Process) -> None:
        """The spare's autogroup back where it was, once (at takeover or SPARE_QUIET_S after its start)."""
        if child.spare is spare and child.spare_shift and spare.returncode is None:
            shift_autogroup(spare.pid, -child.spare_shift)
            child.spare_shift = 0

    async def _pump(self, child: Child, stream: asyncio.StreamReader, logfile, spare_pid: int | None = None) -> None:
        prefix = f"{child.name:<16}| "
        try:
            while line := await stream.readline():
                text = line.decode(errors="replace").rstrip()
                if spare_pid is not None and text == STANDBY_READY:
                    child.spare_ready_pid = spare_pid
                logfile.write(text + "\n")
                logfile.flush()
                if not self.quiet:
                    print(prefix + text, flush=True)
        finally:
            logfile.close()

    async def _stop_child(self, child: Child) -> None:
        spare = child.spare
        if spare is not None and spare.returncode is None:
            try:
                os.killpg(spare.pid, signal.SIGKILL)  # it only imported: nothing to close
            except ProcessLookupError:
                pass
            await spare.wait()
        proc = child.proc
        if proc is None or proc.returncode is not None:
            return
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            await asyncio.wait_for(proc.wait(), STOP_GRACE_S)
        except TimeoutError:
            self.log.warning(f"{child.name} ignored SIGTERM; killing")
            os.killpg(proc.pid, signal.SIGKILL)
            await proc.wait()
        except ProcessLookupError:
            pass

    def children_report(self) -> dict:
        now = time.monotonic()
        return {"children": [{
            "service": c.service, "instance": c.instance,
            "pid": c.proc.pid if c.proc and c.proc.returncode is None else None,
            "uptime_s": round(now - c.started_at, 1) if c.proc and c.proc.returncode is None else 0.0,
            "restarts": c.restarts, "alive": c.alive, "last_exit": c.last_exit, "state": c.state,
            "spare_pid": c.spare.pid if c.spare is not None and c.spare.returncode is None else None,
            "spare_ready": c.spare is not None and c.spare.returncode is None and c.spare_ready_pid == c.spare.pid,
        } for c in self.children]}


def up_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="xm up", description="Run a deployment: the Zenoh router and "
                                     "every service as its own process, restarted when it dies.")
    parser.add_argument("deployment", nargs="?", default="deploy/sim.toml", help="deployment TOML file")
    parser.add_argument("--only", help="comma-separated services to run (default: all of the deployment)")
    parser.add_argument("--host", help="run one host of a multi-host deployment: its router (TLS links to the "
                        "other hosts, access control) and the services placed on it (docs/multihost.md)")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument("--open", action="store_true", help="open the dashboard in a browser if there is a screen")
    parser.add_argument("--quiet", action="store_true", help="logs only to files, not the console")
    parser.add_argument("--standby", action=argparse.BooleanOptionalAction, default=True,
                        help="keep an imported spare process per service that takes over at once when the "
                        "service dies (default: on; a cold restart of a service takes several seconds on "
                        "a busy host, see docs/benchmarks.md; spares cost about twice the memory)")
    args = parser.parse_args(argv)
    try:
        deployment = load_deployment(args.deployment)
        sup = Supervisor(deployment, args.only.split(",") if args.only else None, args.quiet, args.standby,
                         args.host)
    except (ConfigError, HostError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    async def go() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        if args.duration:
            loop.call_later(args.duration, stop.set)
        await sup.run(stop, open_browser=args.open)

    try:
        asyncio.run(go())
    except EndpointError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def query_json(session, selector: str, timeout: float = 2.0) -> list[dict]:
    out = []
    for reply in session.get(selector, timeout=timeout):
        if reply.ok is not None:
            try:
                out.append(json.loads(reply.ok.payload.to_bytes()))
            except ValueError:
                pass
    return out


def status_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="xm status", description="List the services of a running deployment.")
    parser.add_argument("deployment", nargs="?", default="deploy/sim.toml")
    parser.add_argument("--json", action="store_true", help="print the raw health reports")
    args = parser.parse_args(argv)
    try:
        deployment = load_deployment(args.deployment)
        session = open_client(deployment.router)
    except (ConfigError, EndpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:
        print(f"error: no router at {deployment.router} ({exc}); is `xm up` running?", file=sys.stderr)
        return 2
    try:
        reports = query_json(session, "xm/**/@health")
    finally:
        session.close()
    sup = next((r for r in reports if r.get("service") == "deploy"), None)
    if sup is None:
        print(f"no supervisor answered at {deployment.router}; is `xm up {args.deployment}` running?",
              file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(reports, indent=2))
        return 0
    health = {(r["service"], r["instance"]): r for r in reports}
    print(f"{'service':<18}{'pid':>8}{'uptime':>9}{'restarts':>9}  {'state':<11}{'spare':<8}{'status':<9} "
          f"rates (Hz) / rejected, dropped / errors")
    for child in sup["children"]:
        h = health.get((child["service"], child["instance"]), {})
        rates = ", ".join(f"{k.split('/')[-1]}={v:g}" for k, v in h.get("published_hz", {}).items())
        errors = ", ".join(f"{k}={v}" for k, v in h.get("errors", {}).items())
        status = h.get("status", "down" if not child["pid"] else "silent")
        state = child.get("state", "ok")
        if state == "ok" and status == "starting":  # token up, still loading
            state = "recovering" if child["restarts"] else "starting"
        name = f"{child['service']}/{child['instance']}"
        spare = "ready" if child.get("spare_ready") else "loading" if child.get("spare_pid") else "-"
        print(f"{name:<18}{child['pid'] or '-':>8}{child['uptime_s']:>8.0f}s{child['restarts']:>9}  "
              f"{state:<11}{spare:<8}{status:<9} {rates}{counted(h)}{'  ! ' + errors if errors else ''}")
    return 0


def counted(health: dict) -> str:
    """`` | rejected=N (reason=n, ...) dropped=M``: what the service's subscriptions refused and discarded."""
    reasons: dict[str, int] = {}
    for per_key in health.get("rejected", {}).values():
        for reason, n in per_key.items():
            reasons[reason] = reasons.get(reason, 0) + n
    dropped = sum(health.get("dropped", {}).values())
    if not reasons and not dropped:
        return ""
    detail = ", ".join(f"{r}={n}" for r, n in sorted(reasons.items()))
    return f" | rejected={sum(reasons.values())}{f' ({detail})' if detail else ''} dropped={dropped}"


if __name__ == "__main__":
    sys.exit(up_main())
