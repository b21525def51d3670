"""The test as the robot's control board on a pty (contract tests of the robot service)."""

from __future__ import annotations

import itertools
from collections.abc import Callable

import numpy as np

from shared.protocols import robot_board as rb
from tests.conftest import wait_until


def board_feedback(dev, svc, commands: list, q: np.ndarray) -> Callable:
    """``board(until, timeout, what)``: feedback every 4 ms (the robot standing at ``q``), every
    command the service sends (of a plan, the command in force at once) collected into
    ``commands``, until ``until()`` holds; on a timeout the failure names ``what`` and shows the
    service's output."""
    decoder = rb.StreamDecoder()
    sequence = itertools.count()
    zeros = np.zeros(len(q))

    def board(until: Callable, timeout: float, what: str):
        def tick():
            commands.extend(m.command if isinstance(m, rb.PlanFrame) else m for m in decoder.feed(dev.read())
                            if isinstance(m, rb.CommandFrame | rb.PlanFrame))
            seq = next(sequence)
            dev.write(rb.encode_feedback(rb.FeedbackFrame(seq, seq * 4000, 0, q, zeros, zeros)))
            return until()

        return wait_until(tick, timeout, lambda: f"{what}:\n{svc.output()[-3000:]}", period=0.004)

    return board
