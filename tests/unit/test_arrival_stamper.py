"""The simulated board hears the host's commands at their write times although the pty delivers
them late and in bunches: the stamper's probes bound the write times, the board waits for a wire
that still holds a command, spreads the frames of a read the stamper could not make earlier, and
still brakes within 10 ms plus one step when the host stops."""

from __future__ import annotations

import time

import numpy as np

from services.robot.safety import WATCHDOG_TIMEOUT_S
from services.world.arrival_stamper import PROBE, ProbeSplitter
from services.world.devices import BoardDevice
from shared.kinematics import load_robot
from shared.protocols import robot_board as rb

PERIOD = 0.004  # the host's commands, 250 Hz
DT = 0.002  # the world's physics step


def test_probes_split_the_stream_and_bound_the_write_times():
    s = ProbeSplitter()
    s.sent(1.000, 1.0001)
    s.sent(1.001, 1.0011)
    # a stalled pty delivers at 1.050: host bytes, probe 1, host bytes, half of probe 2
    out = s.feed(b"abc" + PROBE + b"de" + PROBE[:5], now=1.050)
    assert out == [(1.0001, b"abc"), (1.000, b""), (1.0011, b"de")]
    out = s.feed(PROBE[5:] + b"f", now=1.060)
    assert out == [(1.001, b""), (1.060, b"f")], "no probe in flight: the read time bounds it"
    assert not s.in_flight
    # bytes that only look like the start of a probe wait for the next read, then pass unchanged
    assert s.feed(PROBE[:3], now=1.07) == []
    assert s.feed(b"xyz", now=1.08) == [(1.08, PROBE[:3] + b"xyz")]


class Sim:
    """Enough of WorldSim for BoardDevice.step: the workcell at rest, time advanced by the caller."""

    def __init__(self, n: int) -> None:
        self.time, self.physics_dt, self.n = 0.0, DT, n

    def joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        return np.full(self.n, 0.01), np.zeros(self.n)

    def set_efforts(self, efforts: np.ndarray) -> None:
        pass


def frame(seq: int, n: int) -> bytes:
    return rb.encode_command(rb.CommandFrame(seq, np.full(n, rb.Mode.POSITION, np.uint8), *np.zeros((5, n))))


def run(tmp_path, deliveries: list[tuple[float, float, list[int], float | None]], until: float) -> BoardDevice:
    """The host writes command ``k`` at ``k * PERIOD``; the pty delivers them as ``deliveries``
    (delivered at, stamp, commands, horizon after them or None); the world steps simulated time along the
    wall time, asking again while ``step`` holds it back, up to ``until``. Returns the device (closed).
    Times count from ``base``, past every real probe of the device's own stamper (no host writes to
    its pty, so it only reports horizons, all earlier)."""
    names = load_robot("workcell").joint_names
    device = BoardDevice(str(tmp_path / "board"), names)
    base = time.monotonic() + 1000.0
    sim, pending = Sim(len(names)), sorted(deliveries, key=lambda d: d[0])
    try:
        wall = 0.0
        while sim.time < until:
            while pending and pending[0][0] <= wall:
                _, stamp, seqs, horizon = pending.pop(0)
                if seqs:
                    device.arrived(b"".join(frame(k, len(names)) for k in seqs), base + stamp)
                if horizon is not None:
                    device.heard_until(base + horizon)
            if sim.time <= wall and device.step(sim, lambda w: w - base, now=base + wall):
                sim.time += DT
            else:  # paced to the wall time, or held back: time passes
                wall += 0.0005
        return device
    finally:
        device.close()


def prompt(seqs, delay: float = 0.0) -> list[tuple[float, float, list[int], float]]:
    """Commands read 0.1 ms after they were written (``delay`` later), each followed by a probe."""
    return [(k * PERIOD + delay + 0.0001, k * PERIOD + delay + 0.0001, [k], k * PERIOD + delay + 0.0001)
            for k in seqs]


def probes(start: float, stop: float) -> list[tuple[float, float, list[int], float]]:
    return [(t, t, [], t) for t in np.arange(start, stop, 0.001)]


def test_a_pty_that_holds_commands_back_starves_no_watchdog(tmp_path):
    deliveries = prompt(range(10))
    # the pty stalls for 50 ms: commands 10-21 arrive together, each bounded by a probe in flight
    deliveries += [(0.095, 0.04 + 0.004 * i + 0.001, [10 + i], 0.04 + 0.004 * i) for i in range(12)]
    # the stamper itself was held up for 40 ms: commands 22-31 in two reads, no probe among them
    deliveries += [(0.128, 0.128, list(range(22, 26)), None), (0.1281, 0.1281, list(range(26, 32)), 0.1281)]
    deliveries += prompt(range(32, 100))
    device = run(tmp_path, deliveries, until=0.4)
    assert device.board.counters["commands"] == 100
    assert device.board.counters["brake_events"] == 0
    assert device.waits > 0, "the board's clock waited for the wire"


def test_the_watchdog_brakes_within_10ms_and_one_step_of_the_last_command(tmp_path):
    device = run(tmp_path, prompt(range(51)) + probes(0.2002, 0.4), until=0.3)
    brake = device.board.last_brake
    assert device.board.counters["brake_events"] == 1 and brake["last_command_sequence"] == 50
    assert WATCHDOG_TIMEOUT_S < brake["at"] - brake["last_command_at"] <= WATCHDOG_TIMEOUT_S + DT + 1e-9


def test_one_command_after_a_real_silence_still_brakes(tmp_path):
    """The host stops for 30 ms after command 20 (the probes show the silence), then sends one
    command, and on: the board brakes once, after command 20."""
    deliveries = prompt(range(21)) + probes(0.0802, 0.11) + prompt(range(21, 60), delay=0.03)
    device = run(tmp_path, deliveries, until=0.25)
    assert device.board.counters["brake_events"] == 1 and device.board.last_brake["last_command_sequence"] == 20

