"""The live overview's alerts (services/panel/alerts.py): each change of the @health rounds once."""

from __future__ import annotations

from services.panel.alerts import Alerts
from services.panel.view import alerts_text


def glove(lost: int = 0, hz: float = 100.0, status: str = "ok") -> dict:
    return {"service": "glove", "instance": "left", "status": status, "decoder": {"frames_lost": lost},
            "published_hz": {"xm/glove/left/tactile": hz}}


def supervisor(state: str, last_exit: int | None = None) -> dict:
    return {"service": "deploy", "instance": "supervisor", "status": "ok",
            "children": [{"service": "glove", "instance": "left", "state": state, "last_exit": last_exit,
                          "restarts": 1}]}


def titles(alerts) -> list[str]:
    return [a.title for a in alerts]


def test_a_service_down_and_back_is_told_once_each():
    a = Alerts(missing_after_s=6.0)
    assert a.update([glove(), supervisor("ok")], 0.0) == []
    down = a.update([supervisor("restarting", -9)], 2.0)
    assert titles(down) == ["glove/left down"] and down[0].level == "error" and "code -9" in down[0].body
    assert a.update([supervisor("recovering", -9)], 4.0) == []  # still down: not told again
    back = a.update([glove(), supervisor("ok")], 6.0)
    assert titles(back) == ["glove/left back"] and back[0].level == "info"


def test_a_service_that_stops_answering_is_down_after_the_grace():
    a = Alerts(missing_after_s=6.0)
    a.update([glove()], 0.0)
    assert a.update([], 4.0) == []  # a missed round is not an outage
    [down] = a.update([], 6.5)
    assert down.title == "glove/left down" and "no @health answer for 6 s" in down.body


def test_device_gaps_and_a_dropped_recording_are_alerts():
    a = Alerts()
    recorder = {"service": "recorder", "instance": "main", "status": "ok", "recording": True,
                "dropped": {"queue_overflow": 0}}
    assert a.update([glove(lost=5), recorder], 0.0) == []  # counters before the first round are the baseline
    gap, dropped = a.update([glove(lost=12), dict(recorder, dropped={"queue_overflow": 3})], 2.0)
    assert gap.title == "glove/left: device gap" and "7 more frames lost (total 12)" in gap.body
    assert dropped.title == "recording dropped messages" and dropped.level == "error" and "3 more" in dropped.body
    assert a.update([glove(lost=12), dict(recorder, dropped={"queue_overflow": 3})], 4.0) == []
    [stopped] = a.update([glove(lost=12, hz=0.0)], 6.0)
    assert "`xm/glove/left/tactile` no longer published" in stopped.body


def test_keys_a_device_stops_at_once_are_one_alert():
    a = Alerts()
    keys = [f"xm/camhub/cam{i}/{kind}" for i in range(7) for kind in ("image", "info")]
    camhub = {"service": "camhub", "instance": "main", "status": "ok", "published_hz": dict.fromkeys(keys, 5.0)}
    assert a.update([camhub], 0.0) == []
    [gap] = a.update([dict(camhub, published_hz=dict.fromkeys(keys, 0.0))], 2.0)
    assert gap.title == "camhub/main: device gap"
    assert gap.body == "`xm/camhub/cam0/image`, `xm/camhub/cam0/info`, `xm/camhub/cam1/image` and 11 more no longer " \
                       "published"


def test_a_service_flipping_between_ok_and_degraded_is_raised_once_a_minute():
    a = Alerts()
    a.update([glove()], 0.0)
    flips = [a.update([glove(status="degraded" if i % 2 else "ok")], 2.0 * i) for i in range(1, 40)]
    raised = [i for i, alerts in enumerate(flips, 1) if alerts]
    assert raised == [1, 31]  # t = 2 s and t = 62 s, not every 4 s
    [err] = a.update([glove(status="error")], 80.0)  # another status is news at once
    assert err.title == "glove/left error"


def test_status_changes_to_error_or_degraded_and_the_list():
    a = Alerts()
    a.update([glove()], 0.0)
    [bad] = a.update([dict(glove(status="degraded"), message="cell map missing")], 2.0)
    assert (bad.level, bad.title, bad.body) == ("warning", "glove/left degraded", "cell map missing")
    assert a.update([dict(glove(status="degraded"), message="cell map missing")], 4.0) == []
    text = alerts_text(list(a.recent))
    assert "**glove/left degraded**: cell map missing" in text and alerts_text([]) == "no alerts"
    assert a.update(["not a report", {"service": 3}], 6.0) == []  # bad replies: no crash
