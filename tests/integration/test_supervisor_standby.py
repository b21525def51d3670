"""`xm up --standby`: a killed service is taken over by its imported spare, and a new spare follows."""

from __future__ import annotations

import os
import signal

import pytest

from tests.conftest import free_endpoint, query_json, wait_for, write_deployment, xm_up

pytestmark = pytest.mark.slow


def test_a_killed_service_is_taken_over_by_its_spare(tmp_path):
    from shared.runtime import open_client

    router = free_endpoint()
    dep = write_deployment(tmp_path / "d.toml", router, {"recorder": {"main": {"directory": str(tmp_path / "rec")}}})
    session = None
    with xm_up(dep, tmp_path / "up.log", "--standby"):
        try:
            def child() -> dict | None:
                nonlocal session
                if session is None:
                    try:
                        session = open_client(router)
                    except Exception:  # the router is not up yet
                        return None
                sup = query_json(session, "xm/deploy/supervisor/@health")
                return sup[0]["children"][0] if sup else None

            first = wait_for(lambda: (c := child()) and c["spare_ready"] and c["state"] == "ok" and c, 60)
            assert first, (tmp_path / "up.log").read_text()
            assert first["spare_pid"] != first["pid"]
            os.kill(first["pid"], signal.SIGKILL)
            after = wait_for(lambda: (c := child()) and c["restarts"] == 1 and c["state"] == "ok" and c, 30)
            assert after and after["pid"] == first["spare_pid"], ((tmp_path / "up.log").read_text(), after)
            health = wait_for(lambda: query_json(session, "xm/recorder/main/@health"), 10)
            assert health and health[0]["pid"] == first["spare_pid"] and health[0]["status"] == "ok"
            again = wait_for(lambda: (c := child()) and c["spare_pid"] not in (None, first["spare_pid"]) and c, 30)
            assert again, "no new spare after the takeover"
            assert wait_for(lambda: (c := child()) and c["spare_ready"], 30), "the new spare never said it was ready"
            assert "from its spare" in (tmp_path / "up.log").read_text()
        finally:
            if session is not None:
                session.close()
