"""The dashboard's Execute controls: which checkpoint the policy serves, the robot's arm state and
a stop button, at the top of the page so that they are always in sight.

Every action is one Zenoh query answered by the service that owns the state: the robot service
arms, disarms and holds (its arm gate, services/robot/service.py), the policy service loads a
checkpoint (@cmd/serve). Stop and disarm therefore work with the policy or trajopt down. Buttons
run on viser's worker threads (blocking queries are fine there); the arm line is refreshed from
the @health reports the panel's status loop collects. **Run execution** runs one execution of the
served policy on a world layout (services/panel/executions.py) on a thread of its own, so STOP and
disarm answer meanwhile; its outcome is logged beside the served checkpoint and in the recordings
directory, counted in the teaching session and listed under the button.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import viser

from services.panel import executions
from services.panel.executions import Execution, ExecutionError, Runner
from services.panel.jobs import Model

log = logging.getLogger("xm")

POLICY = "xm/policy/main"
NO_MODEL = "-"
SILENT_S = 6.0  # the robot's state stays shown this long after its last @health answer (one may come late)
# An arm, disarm or STOP answer stands this long over @health reports, which may have been taken before it
# (a stale "disarmed" would end the execution a press right after arming started).
ANSWER_STANDS_S = 3.0
SHOWN_EXECUTIONS = 5  # the newest executions listed in the folder


class Execute:
    """``query(key, request)`` returns the JSON replies of one query (blocking, [] when nobody
    answered); ``count`` the @health error counter."""

    def __init__(self, server: viser.ViserServer, robot: str, query: Callable[[str, dict], list[dict]],
                 count: Callable[[str], None], session_log: Path | None = None,
                 context: Callable[[], dict] = dict, on_execution: Callable[[Execution], None] | None = None) -> None:
        self.server = server
        self.runner = Runner(query)
        self.session_log = session_log  # every execution also goes here (the recordings directory's log)
        self.context = context  # the teaching session an execution runs in
        self.on_execution = on_execution
        self.recent: list[Execution] = []  # this panel's executions, newest last
        self.robot_key = f"xm/robot/{robot}"
        self.query = query
        self.count = count
        self.armed: bool | None = None  # None: the robot service did not answer
        self._robot_seen = -float("inf")  # when its @health last answered (monotonic)
        self._answered = -float("inf")  # when the robot last answered an arm, disarm or STOP (monotonic)
        self.serving: str | None = None  # the checkpoint the policy serves
        self.method = ""
        self.models: dict[str, Path] = {}
        gui = server.gui
        # first in the page (negative order), outside every folder: never scrolled or folded away
        self.state_md = gui.add_markdown("robot: asking...", order=-3.0)
        gui.add_button("STOP", color="red", icon=viser.Icon.HAND_STOP, order=-2.0).on_click(self._stop)
        with gui.add_folder("Execute", order=-1.0):
            self.arm = gui.add_button_group("robot", ("arm", "disarm"))
            self.arm.on_click(lambda e: self._arm(e.target.value == "arm"))
            self.model = gui.add_dropdown("model", (NO_MODEL,), initial_value=NO_MODEL)
            gui.add_button("Serve").on_click(lambda _e: self._serve())
            self.serve_md = gui.add_markdown("policy: asking...")
            self.layout = gui.add_number("layout seed", initial_value=0, min=0, step=1,
                                         hint="the world resets to this seed's layout, then the robot acts")
            self.seconds = gui.add_number("run seconds", initial_value=9.0, min=1.0, max=executions.MAX_SECONDS,
                                          step=1.0)
            gui.add_button("Run execution", color="green").on_click(self._run)
            self.run_md = gui.add_markdown("no execution yet: the world's success test judges each one")
            # live text below the controls: a line that changes height above them moves them under the cursor
            self.rejections_md = gui.add_markdown("")

    # --- buttons (viser worker threads) ----------------------------------------------------------
    def _ask(self, key: str, request: dict) -> dict | None:
        try:
            replies = self.query(key, request)
        except Exception as exc:  # a dead session: say so, keep the panel alive
            self.count("execute_error")
            self.state_md.content = f"**error**: {exc!r}"
            return None
        return replies[0] if replies else None

    def _stop(self, _event: Any) -> None:
        self.runner.stop.set()  # a running execution ends now (its outcome is still measured)
        reply = self._ask(f"{self.robot_key}/@cmd/hold", {"disarm": True})
        if reply is None or not reply.get("ok"):
            self.count("stop_failed")
            self.armed = None
            self.state_md.content = ("**STOP NOT CONFIRMED**: the robot service did not answer; the board brakes "
                                     "on its own when the robot service is down")
            return
        self.armed, self._answered = bool(reply.get("armed")), time.monotonic()
        self._state_line("stopped: holding")

    def _arm(self, armed: bool) -> None:
        if not armed:
            self.runner.stop.set()  # disarming ends a running execution too
        reply = self._ask(f"{self.robot_key}/@cmd/arm", {"armed": armed})
        if reply is None or not reply.get("ok"):
            self.count("arm_failed")
            why = "the robot service did not answer" if reply is None else reply.get("error", "refused")
            self.state_md.content = f"**{'arm' if armed else 'disarm'} failed**: {why}"
            return
        self.armed, self._answered = bool(reply.get("armed")), time.monotonic()
        self._state_line()

    def _serve(self) -> None:
        path = self.models.get(self.model.value)
        if path is None:
            self.serve_md.content = "**error**: pick a trained model first"
            return
        reply = self._ask(f"{POLICY}/@cmd/serve", {"checkpoint": str(path)})
        if reply is None:
            self.serve_md.content = "**error**: the policy service did not answer"
        elif not reply.get("ok"):
            self.serve_md.content = f"**refused**: {reply.get('error', '')}"
        else:
            self.serve_md.content = f"policy: loading `{path.parent.name}`..."

    def _run(self, event: Any) -> None:
        """Viser worker thread: checks and starts the execution's own thread; a refusal goes to the
        browser that pressed (two browsers at once: one runs, the other is told)."""
        try:
            if self.runner.running:
                raise ExecutionError("an execution is running; wait for its outcome or press STOP")
            if self.armed is not True:
                raise ExecutionError("the robot is not armed: arm it first (the robot never moves unless armed)")
            seed, seconds = int(self.layout.value), float(self.seconds.value)
        except (ExecutionError, TypeError, ValueError) as exc:
            self._refuse(event, str(exc))
            return
        started = threading.Event()
        refusal: list[str] = []
        threading.Thread(target=self._execute, args=(seed, seconds, started, refusal), name="panel-execution",
                         daemon=True).start()
        started.wait(10.0)
        if refusal:
            self._refuse(event, refusal[0])

    def _refuse(self, event: Any, why: str) -> None:
        self.count("execute_refused")
        if event is not None and event.client is not None:
            event.client.add_notification("Execution refused", why, color="red", auto_close_seconds=10.0)
        else:
            self.run_md.content = f"**refused**: {why}"

    def _execute(self, seed: int, seconds: float, started: threading.Event, refusal: list[str]) -> None:
        """Its own thread: the whole execution, then the outcome logged and shown."""
        serving, method = self.serving, self.method or "?"

        def running() -> None:
            self.run_md.content = (f"executing `{serving or method}` on layout {seed} for {seconds:g} s "
                                   "(STOP ends it)...")
            started.set()

        try:
            done = self.runner.run(seed, seconds, self.armed, serving, method, self.context(), on_started=running,
                                   armed_now=lambda: self.armed)
        except ExecutionError as exc:
            if not started.is_set():  # refused before anything moved: the presser is told
                refusal.append(str(exc))
                started.set()
                return
            self.count("execution_error")
            self.run_md.content = f"**execution failed**: {exc}"
            return
        except Exception as exc:  # a dead session: say so, keep the panel alive
            self.count("execution_error")
            log.warning("execution: %r", exc, exc_info=exc)
            self.run_md.content = f"**execution failed**: {exc!r}"
            started.set()
            return
        self._log(done)

    def _log(self, done: Execution) -> None:
        targets = [p for p in (executions.log_path(done.checkpoint) if done.checkpoint else None, self.session_log)
                   if p is not None]
        for path in targets:
            try:
                executions.append(path, done)
            except OSError as exc:
                self.count("execution_log_error")
                log.warning("execution log %s: %r", path, exc)
        self.recent = (self.recent + [done])[-SHOWN_EXECUTIONS:]
        self.run_md.content = "\n\n".join(executions.describe(e) for e in reversed(self.recent))
        if self.on_execution is not None:
            self.on_execution(done)

    # --- state ---------------------------------------------------------------------------------
    def _state_line(self, extra: str = "") -> None:
        if self.armed is None:
            text = "robot: **no answer** (robot service down: the board holds the robot braked)"
        elif self.armed:
            text = "robot: **ARMED**: it follows the plans"
        else:
            text = "robot: **disarmed**: it holds where it stands"
        text += f"; {extra}" if extra else ""
        if self.state_md.content != text:
            self.state_md.content = text

    def update(self, reports: list[dict]) -> None:
        """Event loop (status loop): the arm state and the served checkpoint from @health reports."""
        robot = next((r for r in reports if f"xm/robot/{r.get('instance')}" == self.robot_key
                      and r.get("service") == "robot"), None)
        now = time.monotonic()
        if robot is not None:
            self._robot_seen = now
            if now - self._answered > ANSWER_STANDS_S:
                self.armed = bool(robot.get("armed"))
        elif now - self._robot_seen > SILENT_S:
            self.armed = None
        self._state_line()
        policy = next((r for r in reports if r.get("service") == "policy" and r.get("instance") == "main"), None)
        if policy is None:
            text = "policy: **not running**"
        else:
            self.serving = policy.get("checkpoint")
            self.method = str(policy.get("method", ""))
            loading = policy.get("loading")
            text = f"policy: {policy.get('method', '?')}" + (f" from `{self.serving}`" if self.serving else "")
            if loading:
                text += f"; loading `{loading}`"
            if policy.get("waiting_for"):
                text += f"; switches to `{policy['waiting_for']}` once it is trained"
            if policy.get("load_problem"):
                text += f"; **not served**: {policy['load_problem']}"
        if self.serve_md.content != text:
            self.serve_md.content = text
        trajopt = next((r for r in reports if r.get("service") == "trajopt"), None)
        text = rejections_text(trajopt, robot)
        if self.rejections_md.content != text:
            self.rejections_md.content = text

    def set_models(self, models: list[Model]) -> None:
        """Monitor thread: the trained models to choose from (newest first)."""
        self.models = {m.name: m.checkpoint.resolve() for m in models}
        options = tuple(self.models) or (NO_MODEL,)
        if tuple(self.model.options) != options:
            self.model.options = options
            if self.model.value not in options:
                self.model.value = options[0]

    def health(self) -> dict:
        last = self.recent[-1] if self.recent else None
        return {"armed": self.armed, "serving": self.serving,
                "executions": {"runs": len(self.recent), "running": self.runner.running,
                               "last": None if last is None else {"success": last.success, "seed": last.seed,
                                                                  "stopped": last.stopped,
                                                                  "distances": last.distances,
                                                                  "checkpoint": last.checkpoint}}}



def rejections_text(trajopt: dict | None, robot: dict | None) -> str:
    """What was refused on the way to the robot, with the reasons: trajopt's rejected solves and
    plans, the robot's rejected and (disarmed) ignored trajectories."""
    parts = []
    if trajopt is not None:
        n = trajopt.get("errors", {}).get("solve_rejected", 0)
        last = trajopt.get("last_rejection") or {}
        if n:
            parts.append(f"trajopt rejected {n} solves (last: {last.get('reason') or last.get('status') or '?'})")
        if trajopt.get("last_plan_rejection"):
            parts.append(f"trajopt rejected a plan: {trajopt['last_plan_rejection']}")
    if robot is not None:
        for reason, n in sorted((robot.get("rejections") or {}).items()):
            parts.append(f"robot rejected {n} trajectories: {reason}")
        ignored = robot.get("errors", {}).get("ignored_disarmed", 0)
        if ignored:
            parts.append(f"robot ignored {ignored} trajectories while disarmed")
    return "rejections: " + ("; ".join(parts) if parts else "none")
