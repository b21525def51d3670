"""`xm up --standby`: a killed service is taken over by its imported spare, and a new spare follows."""

from __future__ import annotations

import os
import signal

import pytest

from deploy.supervisor import SPARE_NICE_SHIFT
from shared.realtime import autogroup_nice, can_lower_nice
from tests.conftest import free_endpoint, query_json, wait_for, write_deployment, xm_up

pytestmark = pytest.mark.slow


class Supervised:
    """The supervisor's view of the deployment's one child, through a client session opened once
    the router is up."""

    def __init__(self, router: str) -> None:
        self.router, self.session = router, None

    def child(self) -> dict | None:
        from shared.runtime import open_client

        if self.session is None:
            try:
                self.session = open_client(self.router)
            except Exception:  # the router is not up yet
                return None
        sup = query_json(self.session, "xm/deploy/supervisor/@health")
        return sup[0]["children"][0] if sup else None

    def close(self) -> None:
        if self.session is not None:
            self.session.close()


def test_a_killed_service_is_taken_over_by_its_spare(tmp_path):
    router = free_endpoint()
    dep = write_deployment(tmp_path / "d.toml", router, {"recorder": {"main": {"directory": str(tmp_path / "rec")}}})
    sup = Supervised(router)
    child = sup.child
    with xm_up(dep, tmp_path / "up.log", "--standby"):
        try:
            spare = wait_for(lambda: (c := child()) and c["spare_pid"], 60)
            if can_lower_nice():  # a new spare starts at a small CPU share, and gets the service's back
                assert spare and autogroup_nice(spare) == SPARE_NICE_SHIFT
            first = wait_for(lambda: (c := child()) and c["spare_ready"] and c["state"] == "ok" and c, 60)
            assert first, (tmp_path / "up.log").read_text()
            assert first["spare_pid"] != first["pid"]
            os.kill(first["pid"], signal.SIGKILL)
            after = wait_for(lambda: (c := child()) and c["restarts"] == 1 and c["state"] == "ok" and c, 60)
            assert after and after["pid"] == first["spare_pid"], ((tmp_path / "up.log").read_text(), after)
            if can_lower_nice():
                assert autogroup_nice(after["pid"]) == 0  # a new session's autogroup starts at 0
            health = wait_for(lambda: query_json(sup.session, "xm/recorder/main/@health"), 10)
            assert health and health[0]["pid"] == first["spare_pid"] and health[0]["status"] == "ok"
            again = wait_for(lambda: (c := child()) and c["spare_pid"] not in (None, first["spare_pid"]) and c, 30)
            assert again, "no new spare after the takeover"
            assert wait_for(lambda: (c := child()) and c["spare_ready"], 30), "the new spare never said it was ready"
            assert "from its spare" in (tmp_path / "up.log").read_text()
        finally:
            sup.close()


def test_a_kill_before_the_spare_is_ready_or_after_it_died_still_recovers(tmp_path):
    """The service dies while its spare is not yet reading its "go" (stopped here, as if still
    importing): the spare takes over once it runs. Then the spare itself dies first: the next kill
    is recovered by a fresh process, and a new spare follows."""
    router = free_endpoint()
    dep = write_deployment(tmp_path / "d.toml", router, {"recorder": {"main": {"directory": str(tmp_path / "rec")}}})
    log = tmp_path / "up.log"
    sup = Supervised(router)
    child = sup.child
    with xm_up(dep, log, "--standby"):
        try:
            first = wait_for(lambda: (c := child()) and c["spare_ready"] and c["state"] == "ok" and c, 60)
            assert first, log.read_text()
            spare = first["spare_pid"]
            os.kill(spare, signal.SIGSTOP)  # busy: it cannot read the supervisor's "go"
            try:
                os.kill(first["pid"], signal.SIGKILL)
                waiting = wait_for(lambda: (c := child()) and c["restarts"] == 1 and c, 30)
                assert waiting and waiting["pid"] == spare and waiting["state"] == "recovering", waiting
            finally:
                os.kill(spare, signal.SIGCONT)
            took = wait_for(lambda: (c := child()) and c["state"] == "ok" and c, 30)
            assert took and took["pid"] == spare, (log.read_text(), took)
            health = wait_for(lambda: query_json(sup.session, "xm/recorder/main/@health"), 10)
            assert health and health[0]["pid"] == spare

            nxt = wait_for(lambda: (c := child()) and c["spare_ready"] and c, 60)
            assert nxt, "no new spare after the takeover"
            os.kill(nxt["spare_pid"], signal.SIGKILL)
            assert wait_for(lambda: (c := child()) and c["spare_pid"] is None and c, 10), "the dead spare is listed"
            os.kill(nxt["pid"], signal.SIGKILL)
            cold = wait_for(lambda: (c := child()) and c["restarts"] == 2 and c["state"] == "ok" and c, 60)
            assert cold and cold["pid"] not in (nxt["pid"], nxt["spare_pid"]), (log.read_text(), cold)
            assert wait_for(lambda: (c := child()) and c["spare_ready"] and c, 60), "no spare after a cold start"
        finally:
            sup.close()
