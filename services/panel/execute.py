"""The dashboard's Execute controls: which checkpoint the policy serves, the robot's arm state and
a stop button, at the top of the page so that they are always in sight.

Every action is one Zenoh query answered by the service that owns the state: the robot service
arms, disarms and holds (its arm gate, services/robot/service.py), the policy service loads a
checkpoint (@cmd/serve). Stop and disarm therefore work with the policy or trajopt down. Buttons
run on viser's worker threads (blocking queries are fine there); the arm line is refreshed from
the @health reports the panel's status loop collects.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import viser

from services.panel.jobs import Model

POLICY = "xm/policy/main"
NO_MODEL = "-"
SILENT_S = 6.0  # the robot's state stays shown this long after its last @health answer (one may come late)


class Execute:
    """``query(key, request)`` returns the JSON replies of one query (blocking, [] when nobody
    answered); ``count`` the @health error counter."""

    def __init__(self, server: viser.ViserServer, robot: str, query: Callable[[str, dict], list[dict]],
                 count: Callable[[str], None]) -> None:
        self.server = server
        self.robot_key = f"xm/robot/{robot}"
        self.query = query
        self.count = count
        self.armed: bool | None = None  # None: the robot service did not answer
        self._robot_seen = -float("inf")  # when its @health last answered (monotonic)
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
        reply = self._ask(f"{self.robot_key}/@cmd/hold", {"disarm": True})
        if reply is None or not reply.get("ok"):
            self.count("stop_failed")
            self.armed = None
            self.state_md.content = ("**STOP NOT CONFIRMED**: the robot service did not answer; the board brakes "
                                     "on its own when the robot service is down")
            return
        self.armed = bool(reply.get("armed"))
        self._state_line("stopped: holding")

    def _arm(self, armed: bool) -> None:
        reply = self._ask(f"{self.robot_key}/@cmd/arm", {"armed": armed})
        if reply is None or not reply.get("ok"):
            self.count("arm_failed")
            why = "the robot service did not answer" if reply is None else reply.get("error", "refused")
            self.state_md.content = f"**{'arm' if armed else 'disarm'} failed**: {why}"
            return
        self.armed = bool(reply.get("armed"))
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
            self.armed, self._robot_seen = bool(robot.get("armed")), now
        elif now - self._robot_seen > SILENT_S:
            self.armed = None
        self._state_line()
        policy = next((r for r in reports if r.get("service") == "policy" and r.get("instance") == "main"), None)
        if policy is None:
            text = "policy: **not running**"
        else:
            self.serving = policy.get("checkpoint")
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
        return {"armed": self.armed, "serving": self.serving}



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
