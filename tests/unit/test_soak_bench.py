"""bench/soak.py's bookkeeping: exits it did not cause, and the autogroup boost's process tree."""

from __future__ import annotations

import os

from bench.soak import descendants, unplanned_exits


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
