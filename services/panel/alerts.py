"""Alerts of the live overview, from consecutive rounds of @health replies (no viser, no Zenoh).

``Alerts.update`` compares a round with what earlier rounds showed and returns what changed, once
per change: a service down (the supervisor's report says its process is restarting, or it has not
answered for ``missing_after_s``) and back, a status turning to error or degraded, a device gap (a
glove's lost frames, a robot command gap over the board's watchdog, a camera missing from a
capture, a device key no longer published) and a recording dropping messages. The dashboard
shows each as a toast in every connected browser and keeps the last ones in its Alerts list.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

DEVICE_SERVICES = ("glove", "camhub", "robot", "world")  # their keys stopping is a device gap
KEPT = 20  # alerts listed on the page
SHOWN_KEYS = 3  # keys named in one device-gap alert
REPEAT_S = 60.0  # a service turning degraded (or error) again within this is not raised again


@dataclass(frozen=True)
class Alert:
    level: str  # "error" | "warning" | "info"
    title: str
    body: str
    at: float = field(default_factory=time.time, compare=False)  # wall time, for the list

    @property
    def color(self) -> str:
        return {"error": "red", "warning": "yellow"}.get(self.level, "green")


def _name(report: dict) -> str:
    return f"{report.get('service', '?')}/{report.get('instance', '?')}"


def _number(value: object) -> float:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else 0.0


def _total(value: object) -> float:
    """Sum of the numbers in a (nested) counter dict."""
    if isinstance(value, dict):
        return sum(_total(v) for v in value.values())
    return _number(value)


def counters(report: dict) -> dict[str, float]:
    """The counters whose increase is a device gap or a dropped recording, by alert text."""
    service = report.get("service")
    out: dict[str, float] = {}
    if service == "glove":
        out["frames lost"] = _number((report.get("decoder") or {}).get("frames_lost"))
    elif service == "robot":
        out["command gaps over the board's watchdog"] = _number(
            (report.get("command_stream") or {}).get("gaps_over_watchdog"))
    elif service == "camhub":
        out["captures with a camera missing"] = _total({k: v for k, v in (report.get("errors") or {}).items()
                                                        if k.startswith("camera_missing")})
    elif service == "recorder" and report.get("recording"):
        out["messages dropped from the recording"] = _total(report.get("dropped"))
    return out


class Alerts:
    def __init__(self, missing_after_s: float = 6.0) -> None:
        self.missing_after_s = missing_after_s
        self.last_seen: dict[str, float] = {}  # service/instance -> monotonic time of its last answer
        self.down: set[str] = set()
        self.status: dict[str, str] = {}
        self.counts: dict[str, dict[str, float]] = {}
        self.publishing: dict[str, set[str]] = {}  # device service -> keys it published at a rate > 0
        self.recent: deque[Alert] = deque(maxlen=KEPT)
        self.turned: dict[str, float] = {}  # "<service> <status>" -> when it was last raised (monotonic)

    def update(self, reports: Sequence[dict], now: float) -> list[Alert]:
        """One round of @health replies at monotonic time ``now`` -> the new alerts."""
        out: list[Alert] = []
        answered = {_name(r): r for r in reports if isinstance(r, dict)}
        supervised = {f"{c.get('service')}/{c.get('instance')}": c for r in answered.values()
                      if r.get("service") == "deploy" for c in r.get("children") or [] if isinstance(c, dict)}
        for name in answered:
            self.last_seen[name] = now
        for name in sorted(set(self.last_seen) | set(supervised)):
            child = supervised.get(name)
            if child is not None and child.get("state") in ("restarting", "recovering"):
                why = (f"its process exited (code {child.get('last_exit')}); the supervisor restarts it "
                       f"(restart {child.get('restarts', 0)})")
            elif name not in answered and now - self.last_seen.get(name, now) >= self.missing_after_s:
                why = f"no @health answer for {now - self.last_seen[name]:.0f} s"
            else:
                why = ""
            if why and name not in self.down:
                self.down.add(name)
                out.append(Alert("error", f"{name} down", why))
            elif not why and name in self.down and name in answered:
                self.down.discard(name)
                out.append(Alert("info", f"{name} back", f"answering again, status {answered[name].get('status')}"))
        for name, report in answered.items():
            out += self._status(name, report, now)
            out += self._counters(name, report)
            out += self._keys(name, report)
        self.recent.extend(out)
        return out

    def _status(self, name: str, report: dict, now: float) -> list[Alert]:
        status, before = str(report.get("status", "?")), self.status.get(name)
        self.status[name] = status
        if status == before or status not in ("error", "degraded"):
            return []
        # a service that flips between ok and degraded (trajopt keeping its last safe trajectory while
        # the teacher's hands leave the robot's reach) is raised once a minute, not at every flip
        key = f"{name} {status}"
        if now - self.turned.get(key, -float("inf")) < REPEAT_S:
            return []
        self.turned[key] = now
        return [Alert("error" if status == "error" else "warning", f"{name} {status}",
                      str(report.get("message") or "no message"))]

    def _counters(self, name: str, report: dict) -> list[Alert]:
        now, before = counters(report), self.counts.get(name, {})
        self.counts[name] = now
        out = []
        for what, n in now.items():
            grew = n - before.get(what, n)  # the first round is the baseline, not news
            if grew > 0:
                level = "warning" if report.get("service") != "recorder" else "error"
                title = "recording dropped messages" if report.get("service") == "recorder" else f"{name}: device gap"
                out.append(Alert(level, title, f"{grew:.0f} more {what} (total {n:.0f})"))
        return out

    def _keys(self, name: str, report: dict) -> list[Alert]:
        if report.get("service") not in DEVICE_SERVICES:
            return []
        rates = report.get("published_hz") or {}
        now = {k for k, hz in rates.items() if _number(hz) > 0}
        stopped = sorted((self.publishing.get(name, set()) - now) & set(rates))
        self.publishing[name] = now
        if not stopped:
            return []
        # one alert per service and round: a camera rig stalling stops 14 keys at once
        shown = ", ".join(f"`{k}`" for k in stopped[:SHOWN_KEYS])
        more = f" and {len(stopped) - SHOWN_KEYS} more" if len(stopped) > SHOWN_KEYS else ""
        return [Alert("warning", f"{name}: device gap", f"{shown}{more} no longer published")]
