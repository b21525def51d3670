"""The Execute folder's arm state: the robot's answer to a press stands over @health reports for a
few seconds (a report taken before the press would otherwise undo it, and a stale "disarmed" would
end an execution started right after arming); after that the reports rule again."""

from __future__ import annotations

import viser

from services.panel import execute
from services.panel.execute import Execute
from tests.conftest import free_port


def test_an_arm_answer_stands_over_an_older_health_report_then_reports_rule():
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        panel = Execute(server, "workcell", lambda key, request: [{"ok": True, "armed": True}], lambda name: None)
        report = [{"service": "robot", "instance": "workcell", "armed": False}]
        panel.update(report)
        assert panel.armed is False
        panel._arm(True)
        assert panel.armed is True
        panel.update(report)  # taken before the press: the answer stands
        assert panel.armed is True
        panel._answered -= execute.ANSWER_STANDS_S + 0.1
        panel.update(report)
        assert panel.armed is False
    finally:
        server.stop()
