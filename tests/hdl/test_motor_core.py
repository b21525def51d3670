"""cocotb on Icarus: the motor-control core (hdl/motor): watchdog, commutation, PWM, whole axis.

Time scaling: the watchdog counts microseconds from a prescaler of CLK_PER_US clocks (50 on the
50 MHz board). The tests build it with CLK_PER_US = 2, so one 10 ns simulator clock stands for
0.5 us of board time: the real 10 ms timeout is 20 000 clocks (200 us of simulated time), and the
test checks it to the clock. The PWM runs with a short period (P = 100) for the same reason; the
logic does not depend on P.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from tests.hdl._cocotb import HDL_MARKS, ROOT, run_cocotb

HDL = ROOT / "hdl" / "motor"
AXIS_SOURCES = ["motor_axis.v", "motor_watchdog.v", "encoder_spi.v", "pid_axis.v", "commutation.v", "sine_rom.v",
                "pwm_center.v"]
CLK_PER_US = 2
pytestmark = HDL_MARKS


def run(tmp_path: Path, toplevel: str, sources: list[str], params: dict, tests: list[str]) -> None:
    run_cocotb([HDL / s for s in sources], toplevel, "test_motor_core", tmp_path, len(tests), params, tests)


def test_watchdog_fires_at_10_ms(tmp_path):
    run(tmp_path, "motor_watchdog", ["motor_watchdog.v"], {"CLK_PER_US": CLK_PER_US}, ["watchdog_10ms"])


def test_commutation_phases(tmp_path):
    run(tmp_path, "commutation", ["commutation.v", "sine_rom.v"], {"POLE_PAIRS": 4},
        ["commutation_bit_exact", "commutation_120_degrees"])


def test_pwm_symmetry_duty_deadtime(tmp_path):
    run(tmp_path, "pwm_center", ["pwm_center.v"], {"W": 11, "DEADTIME": 3}, ["pwm_periods"])


def test_axis_encoder_brake_and_drive(tmp_path):
    run(tmp_path, "motor_axis", AXIS_SOURCES, {"CLK_PER_US": CLK_PER_US, "SPI_HALF": 2, "DEADTIME": 3},
        ["axis_end_to_end"])


# ---- cocotb side (runs inside the simulator; no test_ prefix so pytest does not collect it) ----
try:
    import cocotb
    from cocotb.clock import Clock
    from cocotb.triggers import ClockCycles, FallingEdge, ReadOnly, RisingEdge, with_timeout
    from cocotb.utils import get_sim_time
except ImportError:  # pragma: no cover
    cocotb = None


async def reset(dut) -> None:
    cocotb.start_soon(Clock(dut.clk, 10, unit="ns").start())
    dut.rst.value = 1
    await ClockCycles(dut.clk, 3)
    dut.rst.value = 0
    await RisingEdge(dut.clk)


def sine_table() -> list[int]:
    sys.path.insert(0, str(HDL))
    from gen_sine_rom import table

    return table()


def commutation_model(angle: int, offset: int, amp: int, pole_pairs: int = 4) -> list[int]:
    """Bit-exact: quarter-wave table, 1024 steps per electrical turn, (amp * s) >> 15 (floor)."""
    t = sine_table()
    theta = (angle * pole_pairs + offset + 8192) % 32768
    out = []
    for k in range(3):
        idx = ((theta - k * 10923) % 32768) >> 5
        i = idx & 0xFF
        s = t[255 - i] if idx & 0x100 else t[i]
        out.append((amp * (-s if idx & 0x200 else s)) >> 15)
    return out


if cocotb is not None:

    @cocotb.test()
    async def watchdog_10ms(dut):
        dut.kick.value = 0
        dut.timeout_us.value = 10_000
        await reset(dut)
        assert dut.expired.value == 1, "must brake from power-up until the first command"
        for trial in range(3):
            await FallingEdge(dut.clk)
            dut.kick.value = 1
            await FallingEdge(dut.clk)
            dut.kick.value = 0
            kicked = get_sim_time("ns")
            await RisingEdge(dut.clk)
            await ReadOnly()
            assert dut.expired.value == 0
            await with_timeout(RisingEdge(dut.expired), 400, "us")
            await ReadOnly()
            cycles = round((get_sim_time("ns") - kicked) / 10)
            # 10 ms at CLK_PER_US clocks per us, counted from the kick, to one clock
            assert abs(cycles - 10_000 * CLK_PER_US) <= 1, f"trial {trial}: expired after {cycles} clocks"
            assert int(dut.trips.value) == trial + 1
        # Commands every 9 ms (scaled) keep it alive.
        for _ in range(5):
            await FallingEdge(dut.clk)
            dut.kick.value = 1
            await FallingEdge(dut.clk)
            dut.kick.value = 0
            await ClockCycles(dut.clk, 9_000 * CLK_PER_US)
            assert dut.expired.value == 0
        assert int(dut.trips.value) == 3

    async def commutate(dut, angle: int, offset: int, amp: int) -> list[int]:
        await FallingEdge(dut.clk)
        dut.angle.value = angle
        dut.offset.value = offset
        dut.amplitude.value = amp
        dut.start.value = 1
        await FallingEdge(dut.clk)
        dut.start.value = 0
        for _ in range(20):
            await RisingEdge(dut.clk)
            await ReadOnly()
            if dut.done.value == 1:
                break
        else:
            raise AssertionError("commutation never finished")
        await FallingEdge(dut.clk)  # outputs are registered together with done
        return [dut.va.value.to_signed(), dut.vb.value.to_signed(), dut.vc.value.to_signed()]

    @cocotb.test()
    async def commutation_bit_exact(dut):
        import random

        rng = random.Random(3)
        dut.start.value = 0
        await reset(dut)
        for _ in range(150):
            angle, offset, amp = rng.randrange(32768), rng.randrange(32768), rng.randint(-1250, 1250)
            got = await commutate(dut, angle, offset, amp)
            assert got == commutation_model(angle, offset, amp), (angle, offset, amp)
            theta = 2 * math.pi * ((angle * 4 + offset) % 32768) / 32768
            for k, v in enumerate(got):  # against the ideal sine: half a table step of phase, 1 count
                ideal = amp * math.sin(theta + math.pi / 2 - k * 2 * math.pi / 3)
                assert abs(v - ideal) <= abs(amp) * math.pi / 1024 + 1.0, (angle, amp, k, v, ideal)

    @cocotb.test()
    async def commutation_120_degrees(dut):
        amp = 600
        dut.start.value = 0
        await reset(dut)
        thetas, rows = [], []
        for j in range(96):  # one electrical turn = a quarter of a mechanical turn at 4 pole pairs
            angle = j * (8192 // 96)
            thetas.append(2 * math.pi * (angle * 4 % 32768) / 32768)
            rows.append(await commutate(dut, angle, 0, amp))
        phases, amps = [], []
        for k in range(3):  # least-squares fit v = a sin(theta) + b cos(theta)
            a = sum(r[k] * math.sin(t) for r, t in zip(rows, thetas, strict=False)) * 2 / len(rows)
            b = sum(r[k] * math.cos(t) for r, t in zip(rows, thetas, strict=False)) * 2 / len(rows)
            amps.append(math.hypot(a, b))
            phases.append(math.degrees(math.atan2(b, a)))
        for k in range(3):
            assert abs(amps[k] - amp) < 0.01 * amp, f"phase {k} amplitude {amps[k]:.1f}"
            want = (90 - 120 * k + 180) % 360 - 180  # a leads the rotor by 90 deg; b, c 120 deg behind
            assert abs((phases[k] - want + 180) % 360 - 180) < 0.5, f"phase {k} at {phases[k]:.2f} deg"
        assert all(abs(sum(r)) <= 0.01 * amp for r in rows)  # a balanced three-phase set

    async def record_period(dut, n_clocks: int) -> list[tuple[int, int, int, int]]:
        out = []
        for _ in range(n_clocks):
            await RisingEdge(dut.clk)
            await ReadOnly()
            out.append((int(dut.hi.value), int(dut.lo.value), int(dut.adc_trigger.value),
                        int(dut.period_start.value)))
        return out

    @cocotb.test()
    async def pwm_periods(dut):
        P, DT = 100, 3
        dut.period_half.value = P
        duties = [(50, 0, 100), (20, 99, 4), (3, 60, 2)]
        dut.duty_a.value, dut.duty_b.value, dut.duty_c.value = duties[0]
        dut.brake.value = 0
        await reset(dut)
        while True:  # align to a period start
            await RisingEdge(dut.clk)
            await ReadOnly()
            if dut.period_start.value == 1:
                break
        await record_period(dut, 2 * P)  # the first full period, duties[0] taken at its end valley
        await FallingEdge(dut.clk)
        for d_now, d_next in zip(duties, duties[1:] + [duties[-1]], strict=False):
            trace = await record_period(dut, P)
            await FallingEdge(dut.clk)
            dut.duty_a.value, dut.duty_b.value, dut.duty_c.value = d_next  # mid-period: waits for the valley
            trace += await record_period(dut, P)
            await FallingEdge(dut.clk)
            check_period(trace, d_now, P, DT)
        dut.brake.value = 1
        await ClockCycles(dut.clk, 3)
        await ReadOnly()
        assert int(dut.hi.value) == 0 and int(dut.lo.value) == 0b111  # shorted windings

    def check_period(trace, duties, P, DT) -> None:
        assert len(trace) == 2 * P
        trig = [i for i, r in enumerate(trace) if r[2]]
        assert len(trig) == 1, f"one ADC trigger per period, got {trig}"
        for ph, d in enumerate(duties):
            hi = [i for i, r in enumerate(trace) if r[0] >> ph & 1]
            lo = [i for i, r in enumerate(trace) if r[1] >> ph & 1]
            assert not set(hi) & set(lo), "shoot-through"
            assert len(hi) == 2 * max(d - DT, 0), f"phase {ph} duty {d}: {len(hi)} high clocks"
            assert len(lo) == 2 * (P - d), f"phase {ph} duty {d}: {len(lo)} low clocks"
            if hi:
                assert hi == list(range(hi[0], hi[-1] + 1)), "one contiguous pulse"
                # centred on the peak: the trigger is the first of the two middle clocks
                assert (hi[0] + hi[-1]) / 2 == trig[0] + 0.5
                if lo:  # dead time on both edges
                    before = max(i for i in lo if i < hi[0])
                    after = min(i for i in lo if i > hi[-1])
                    assert hi[0] - before - 1 == DT and after - hi[-1] - 1 == DT

    class EncoderModel:
        """A1333-style slave: answers every 16-bit frame with {error, angle}, mode 3, MSB first."""

        def __init__(self, dut) -> None:
            self.dut = dut
            self.angle = 0
            self.error = 0
            self.commands: list[int] = []
            cocotb.start_soon(self.serve())

        async def serve(self) -> None:
            dut = self.dut
            dut.enc_miso.value = 1
            while True:
                await FallingEdge(dut.enc_cs_n)
                word = (self.error << 15) | (self.angle & 0x7FFF)
                cmd = 0
                for bit in range(16):
                    await FallingEdge(dut.enc_sclk)
                    dut.enc_miso.value = (word >> (15 - bit)) & 1
                    await RisingEdge(dut.enc_sclk)
                    cmd = (cmd << 1) | int(dut.enc_mosi.value)
                self.commands.append(cmd)

    @cocotb.test()
    async def axis_end_to_end(dut):
        P = 200
        enc = EncoderModel(dut)
        enc.angle = 32000  # near the wrap, to test the multi-turn unwrapping
        dut.cmd_valid.value = 0
        dut.cmd_mode.value = 0
        dut.cmd_pos.value = 0
        dut.cmd_vel.value = 0
        dut.cmd_ff.value = 0
        dut.watchdog_us.value = 500  # scaled: 1000 clocks = 5 PWM periods
        dut.period_half.value = P
        dut.elec_offset.value = 0
        dut.kp.value, dut.ki.value, dut.kd.value, dut.i_clamp.value = 64, 0, 0, 20
        await reset(dut)
        await ClockCycles(dut.clk, 4 * P)
        assert enc.commands and all(c == 0x2000 for c in enc.commands)
        assert dut.braking.value == 1 and int(dut.gate_lo.value) == 0b111, "no command yet: brake"
        assert dut.position.value.to_signed() == 32000
        for step in (500, 500):  # forward across the 2^15 wrap, twice
            enc.angle = (enc.angle + step) % 32768
            await ClockCycles(dut.clk, 2 * P + 50)
        assert dut.position.value.to_signed() == 33000, "multi-turn position across the wrap"
        # Effort mode: a command drives the phases (gates switch, no brake).
        await FallingEdge(dut.clk)
        dut.cmd_mode.value = 3
        dut.cmd_ff.value = 60
        dut.cmd_valid.value = 1
        await FallingEdge(dut.clk)
        dut.cmd_valid.value = 0
        highs = 0
        for _ in range(4 * P):
            await RisingEdge(dut.clk)
            highs += int(dut.gate_hi.value) != 0
            assert dut.braking.value == 0 or dut.wd_expired.value == 1
        assert highs > 0 and dut.wd_expired.value == 0
        # Silence: the watchdog brakes after 500 (scaled) us = 1000 clocks from the command.
        await with_timeout(RisingEdge(dut.wd_expired), 20, "us")
        await ClockCycles(dut.clk, 3)
        await ReadOnly()
        assert dut.braking.value == 1 and int(dut.gate_hi.value) == 0 and int(dut.gate_lo.value) == 0b111
        # A sensor error also brakes, even with fresh commands.
        await FallingEdge(dut.clk)
        dut.cmd_valid.value = 1
        await FallingEdge(dut.clk)
        dut.cmd_valid.value = 0
        enc.error = 1
        await ClockCycles(dut.clk, 2 * P + 50)
        await ReadOnly()
        assert dut.enc_error.value == 1 and dut.braking.value == 1
