"""The policy service steps its memory once per sample period of sim time, skipped ticks included."""

from services.policy.service import MAX_CATCH_UP, policy_steps


def test_one_step_per_elapsed_sample_period():
    assert policy_steps(1.00, None, 0.02) == 1  # the first tick
    assert policy_steps(1.02, 1.00, 0.02) == 1
    assert policy_steps(1.10, 1.00, 0.02) == 5  # four ticks skipped by a late process
    assert policy_steps(1.00, 1.00, 0.02) == 1  # never fewer than one per tick


def test_a_long_stall_is_not_caught_up():
    assert policy_steps(10.0, 1.0, 0.02) == MAX_CATCH_UP
