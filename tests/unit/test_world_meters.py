"""The world's own account of its pauses: wire holds and gaps between clock messages."""

from services.world.devices import HoldLog
from services.world.service import GapMeter


def test_hold_log_measures_each_episode_of_refused_steps():
    holds = HoldLog()
    holds.stepped(0.0, 0.0)  # a step without a hold is no episode
    holds.waiting(1.0, 0.95)
    holds.waiting(1.05, 0.95)
    holds.stepped(1.3, 1.29)
    holds.waiting(2.0, 1.99)
    holds.stepped(2.01, 2.0)
    stats = holds.stats()
    assert stats["count"] == 2 and stats["over_100ms"] == 1
    assert stats["longest_s"] == 0.3
    assert stats["last_long"] == {"held_s": 0.3, "at": 1.0, "horizon_age_s": 0.05, "horizon_moved_s": 0.34}


def test_gap_meter_reports_the_longest_gap_and_when_it_began():
    meter = GapMeter()
    for t, waited in ((10.0, 0.0), (10.01, 0.0), (10.02, 0.001), (11.2, 0.9), (11.21, 0.9)):
        meter.sent(t, waited)
    stats = meter.stats()
    assert stats == {"longest_s": 1.18, "began_after_s": 0.02, "waited_for_cpu_s": 0.899}
