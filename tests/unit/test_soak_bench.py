"""bench/soak.py's bookkeeping: exits it did not cause, and the autogroup boost's process tree."""

from __future__ import annotations

import os

from bench.soak import descendants, unplanned_exits
from tests.conftest import wait_for


def test_exits_beyond_the_soaks_kills_are_unplanned(tmp_path):
    log = tmp_path / "up.log"
    log.write_text("\n".join([
        "16:10:12.347 INFO  supervisor: started camhub/main pid=19260",
        "16:16:50.224 WARNING supervisor: trajopt/main exited code=-9 ran_s=300.7 restart_in_s=0.0",
        "16:20:57.635 WARNING supervisor: camhub/main exited code=-6 ran_s=645.3 restart_in_s=0.0",
        "16:21:50.922 WARNING supervisor: camhub/main exited code=-9 ran_s=53.3 restart_in_s=0.0",
        "16:22:50.958 WARNING supervisor: recorder/main exited code=-9 ran_s=481.1 restart_in_s=0.0",
        "16:23:00.000 WARNING supervisor: recorder/main exited code=1 ran_s=9.0 restart_in_s=0.0",
    ]))
    kills = [{"service": "trajopt/main"}, {"service": "camhub/main"}]  # the recorder was never killed
    assert unplanned_exits(log, kills) == [
        {"at": "16:20:57.635", "service": "camhub/main", "code": -6, "ran_s": 645.3},
        {"at": "16:22:50.958", "service": "recorder/main", "code": -9, "ran_s": 481.1},
        {"at": "16:23:00.000", "service": "recorder/main", "code": 1, "ran_s": 9.0},
    ]
    assert unplanned_exits(tmp_path / "missing.log", kills) == []


def test_the_boosted_tree_holds_the_soak_and_its_children_only():
    tree = descendants([os.getpid()])
    assert os.getpid() in tree and os.getppid() not in tree


def test_a_brake_is_put_on_the_host_only_when_its_gap_ends_at_a_probe_stall():
    from bench._host_probe import attribute_brakes, steal_jiffies

    events = [{"host_gap": {"at_unix": 100.00}}, {"host_gap": {"at_unix": 200.0}}, {"host_gap": None}]
    stalls = [{"at_unix": 100.03, "late_ms": 12.0, "steal_ms_per_cpu": [10, 0]}, {"at_unix": 200.2, "late_ms": 9.0}]
    assert attribute_brakes(events, stalls) == 2
    assert [e["host_stall_near"] for e in events] == [True, False, False]
    assert events[0]["hypervisor_steal_near"] and not events[1]["hypervisor_steal_near"]
    assert all(isinstance(j, int) for j in steal_jiffies())


def test_the_boost_moves_each_autogroup_once_however_many_processes_share_it():
    import subprocess
    import sys

    from bench.soak import shift_autogroups
    from shared.realtime import autogroup_nice

    # a session (one autogroup) of two processes: a service and its child
    child = "subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])"
    leader = subprocess.Popen([sys.executable, "-c", f"import subprocess, sys, time; {child}; time.sleep(60)"],
                              start_new_session=True)
    try:
        assert wait_for(lambda: len(descendants([leader.pid])) == 2, 10)
        if autogroup_nice(leader.pid) is None:
            return  # no autogroups on this kernel
        done: set[str] = set()
        assert shift_autogroups(descendants([leader.pid]), 2, done) == 1
        assert shift_autogroups(descendants([leader.pid]), 2, done) == 0
        assert autogroup_nice(leader.pid) == 2
    finally:
        os.killpg(leader.pid, 9)
        leader.wait()
