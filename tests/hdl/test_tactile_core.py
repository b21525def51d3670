"""cocotb on Icarus: the whole readout core (4 x 4 lines to keep simulation short) against a Python
model of the analog side (RC-filtered DAC bitstreams driving a capacitive/resistive cell matrix,
current-mode delta-sigma ADC integrators and comparators), with register access over the UART.

Tolerance: after normalising each excitation line by a reference cell (reception line 0, a pure
conductance, like a reference resistor), every cell's recovered admittance G + C(1 - e^-jW) is
within 5 % of the matrix's largest cell admittance, from one 1024-sample window."""

from __future__ import annotations

import numpy as np

from tests.hdl._cocotb import HDL_MARKS, ROOT, run_cocotb

HDL = ROOT / "hdl" / "tactile"
NTX = NRX = 4
UART_DIV = 4
SOURCES = ["tactile_core.v", "tactile_packer.v", "tactile_regs.v", "tactile_cmd.v", "tactile_framer.v", "uart.v",
           "crc32.v"]
WINDOW = 1024
CYCLES = [3, 5, 7, 11]  # cycles per window: high oversampling, as the real modulators run at MHz


pytestmark = HDL_MARKS


def test_core_registers_and_impedances(tmp_path):
    params = {"NTX": NTX, "NRX": NRX, "UART_DIV": UART_DIV, "CLK_PER_US": 10,
              "LUT_FILE": f'"{HDL / "sine_lut.hex"}"'}
    run_cocotb([HDL / s for s in SOURCES], "tactile_core", "test_tactile_core", tmp_path, expect=5, parameters=params)


# ---- cocotb side (runs inside the simulator; no test_ prefix so pytest does not collect it) ----
try:
    import cocotb
    from cocotb.clock import Clock
    from cocotb.triggers import FallingEdge, ReadOnly, RisingEdge, Timer
    from cocotb.utils import get_sim_time
except ImportError:  # pragma: no cover
    cocotb = None

if cocotb is not None:
    from shared.protocols import tactile

    BIT_NS = UART_DIV * 10

    async def uart_send(dut, data: bytes) -> None:
        for byte in data:
            for bit in [0] + [(byte >> i) & 1 for i in range(8)] + [1]:
                dut.uart_rx.value = bit
                await Timer(BIT_NS, unit="ns")

    async def uart_monitor(dut, decoder: tactile.StreamDecoder, out: list, raw: bytearray | None = None) -> None:
        while True:
            await FallingEdge(dut.uart_tx)
            await Timer(BIT_NS // 2, unit="ns")
            byte = 0
            for i in range(8):
                await Timer(BIT_NS, unit="ns")
                byte |= int(dut.uart_tx.value) << i
            await Timer(BIT_NS, unit="ns")
            if raw is not None:
                raw.append(byte)
            out.extend(decoder.feed(bytes([byte])))

    async def start(dut, raw: bytearray | None = None):
        cocotb.start_soon(Clock(dut.clk, 10, unit="ns").start())
        dut.rst.value = 1
        dut.uart_rx.value = 1
        dut.adc_cmp.value = 0
        dut.imu_valid.value = 0
        dut.imu_first.value = 0
        dut.imu_data.value = 0
        for _ in range(4):
            await RisingEdge(dut.clk)
        dut.rst.value = 0
        decoder = tactile.StreamDecoder()
        out: list = []
        cocotb.start_soon(uart_monitor(dut, decoder, out, raw))
        return decoder, out

    async def command(dut, out: list, address: int, value: int | None = None,
                      timeout_us: int = 20) -> tactile.RegisterReply:
        await uart_send(dut, tactile.encode_command(address, value))
        for _ in range(10 * timeout_us):
            replies = [o for o in out if isinstance(o, tactile.RegisterReply)]
            if replies:
                out.remove(replies[0])
                return replies[0]
            await Timer(100, unit="ns")
        raise AssertionError(f"no reply to register {address:#x}")

    @cocotb.test()
    async def registers_over_uart(dut) -> None:
        decoder, out = await start(dut)
        model = tactile.RegisterFile()
        for addr, value in [(tactile.REG_FRAME_COUNT, None), (tactile.REG_FRAME_COUNT, 5),  # before any frame
                            (tactile.REG_ID, None), (tactile.REG_ID, 5), (0x0002, None), (0x0200, 1),
                            (tactile.REG_FREQ_BASE + 4, None), (tactile.REG_TICK_DIV, 0x12345),
                            (tactile.REG_TICK_DIV, None), (tactile.REG_FREQ_BASE + 60, 0xDEADBEEF),
                            (tactile.REG_FREQ_BASE + 60, None), (tactile.REG_RX_ENABLE, 0x3F),
                            # every kind of register: defaults, truncation, one-bit registers, bad addresses
                            (tactile.REG_WINDOW, None), (tactile.REG_TX_ENABLE, None), (tactile.REG_TX_ENABLE, 0xABCDE),
                            (tactile.REG_TX_ENABLE, None), (tactile.REG_RX_ENABLE, None), (tactile.REG_IMU_ENABLE, 3),
                            (tactile.REG_IMU_ENABLE, None), (tactile.REG_CONTROL, None), (tactile.REG_FREQ_BASE, None),
                            (tactile.REG_FREQ_BASE + 28, 0x89ABCDEF), (tactile.REG_FREQ_BASE + 28, None),
                            (tactile.REG_FREQ_BASE + 32, None), (0x0101, None), (0x0140, 7), (0x0020, None)]:
            got = await command(dut, out, addr, value)
            want = model.handle(tactile.RegisterCommand(addr, value))
            assert (got.address, got.value, got.status) == (want.address, want.value, want.status), (got, want)
        # A corrupted command is dropped (no reply) and counted; the next one works.
        bad = bytearray(tactile.encode_command(tactile.REG_WINDOW, 9))
        bad[8] ^= 0xFF
        await uart_send(dut, bytes(bad))
        assert (await command(dut, out, tactile.REG_WINDOW, None)).value == 256
        assert int(dut.u_cmd.rejected.value) == 1

    @cocotb.test()
    async def commands_while_streaming(dut) -> None:
        """Three commands back to back (45 bytes, no waiting for replies) while frames stream: the
        first one's reply can wait behind a frame (37 us on the link) while the other two arrive; they
        wait in the parser's RX FIFO. Every command gets its reply, in order, equal to RegisterFile's,
        and the frames stay intact."""
        decoder, out = await start(dut)
        model = tactile.RegisterFile()
        for addr, value in [(tactile.REG_TICK_DIV, 20), (tactile.REG_WINDOW, 128), (tactile.REG_RX_ENABLE, 0xF)]:
            await command(dut, out, addr, value, timeout_us=60)
            model.handle(tactile.RegisterCommand(addr, value))
        rng = np.random.default_rng(3)
        pool = [tactile.REG_ID, tactile.REG_TX_ENABLE, tactile.REG_WINDOW, tactile.REG_TICK_DIV, 0x0101,
                tactile.REG_FREQ_BASE + 8, tactile.REG_FREQ_BASE + 60]
        replies: list = []
        sent = 0
        for _ in range(8):
            cmds = []
            for _ in range(3):
                addr = pool[int(rng.integers(len(pool)))]
                write = addr in (tactile.REG_ID, tactile.REG_FREQ_BASE + 8, tactile.REG_FREQ_BASE + 60, 0x0101) \
                    and bool(rng.integers(2))
                cmds.append((addr, int(rng.integers(1 << 32)) if write else None))
            await Timer(int(rng.integers(1, 40)), unit="us")  # somewhere in the frame stream
            await uart_send(dut, b"".join(tactile.encode_command(a, v) for a, v in cmds))
            sent += len(cmds)
            for a, v in cmds:
                want = model.handle(tactile.RegisterCommand(a, v))
                replies.append(((a, v), (want.address, want.value, want.status)))
        for _ in range(200):
            if sum(isinstance(o, tactile.RegisterReply) for o in out) >= sent:
                break
            await Timer(1, unit="us")
        got = [(r.address, r.value, r.status) for r in out if isinstance(r, tactile.RegisterReply)]
        frames = [o for o in out if isinstance(o, tactile.TactileFrame)]
        assert got == [w for _, w in replies], (got, replies)
        assert len(frames) >= 4 and decoder.stats["crc_errors"] == 0 and decoder.stats["bytes_discarded"] == 0, \
            (len(frames), decoder.stats)
        assert int(dut.u_cmd.rejected.value) == 0

    @cocotb.test()
    async def impedances_from_modelled_cells(dut) -> None:
        decoder, out = await start(dut)
        rng = np.random.default_rng(5)
        G = rng.uniform(0.0, 0.1, (NTX, NRX))
        C = rng.uniform(0.0, 2.0, (NTX, NRX))
        G[:, 0], C[:, 0] = 0.2, 0.0  # reference cells
        for k, c in enumerate(CYCLES):
            await command(dut, out, tactile.REG_FREQ_BASE + 4 * k, c * 2**32 // WINDOW)
        await command(dut, out, tactile.REG_TICK_DIV, 24)
        await command(dut, out, tactile.REG_WINDOW, WINDOW)
        cocotb.start_soon(analog(dut, G, C))
        frames = []
        for _ in range(20000):
            await Timer(1, unit="us")
            frames = [o for o in out if isinstance(o, tactile.TactileFrame)]
            if len(frames) >= 3:
                break
        assert len(frames) >= 3, decoder.stats
        assert decoder.stats["crc_errors"] == 0 and decoder.stats["bytes_discarded"] == 0
        f = frames[2]  # settled: a whole window with the final configuration
        assert f.status == 0 and (f.tx_mask, f.rx_mask) == (0x000F, 0x000F)
        assert [fr.sequence for fr in frames] == list(range(frames[0].sequence, frames[0].sequence + len(frames)))
        meas = f.impedance[:NTX, :NRX].astype(np.complex128)
        W = 2 * np.pi * np.array(CYCLES)[:, None] / WINDOW
        Y = G + C * (1 - np.exp(-1j * W))
        dut._log.info("raw\n%s", meas)
        est = meas / meas[:, :1] * 0.2
        err = np.abs(est - Y).max() / np.abs(Y).max()
        dut._log.info("relative error %.4f; recovered\n%s\nmodel\n%s", err, np.round(est, 4), np.round(Y, 4))
        assert err < 0.05, err
        assert np.all(f.impedance[NTX:, :] == 0)

    @cocotb.test()
    async def imu_samples_in_frames(dut) -> None:
        """IMU words in on imu_*: no samples in frames until imu_enable is set, then every completed
        sample in exactly one frame, in order, with the frame bytes equal to encode_frame's; more than
        8 in a window keeps the last 8 and sets status bit 3."""
        raw = bytearray()
        decoder, out = await start(dut, raw)
        await command(dut, out, tactile.REG_TICK_DIV, 20)
        await command(dut, out, tactile.REG_WINDOW, 512)  # 102 us windows; a frame with 8 samples: 76 us
        rng = np.random.default_rng(11)
        samples = rng.integers(-32768, 32768, (40, 6))
        samples[0] = [-32768, 32767, 0, -1, 1, 2048]
        sent = []  # index into samples of each sample completed while imu_enable was set

        async def push(i: int, gaps: bool) -> None:
            for w in range(6):  # inputs change between clock edges, as from a synchronous source
                await FallingEdge(dut.clk)
                dut.imu_data.value = int(samples[i, w]) & 0xFFFF
                dut.imu_first.value = int(w == 0)
                dut.imu_valid.value = 1
                await FallingEdge(dut.clk)
                dut.imu_valid.value = 0
                dut.imu_first.value = 0
                if gaps:  # words need not come on consecutive clocks
                    for _ in range(int(rng.integers(0, 4))):
                        await FallingEdge(dut.clk)

        async def frames_seen() -> list:
            return [o for o in out if isinstance(o, tactile.TactileFrame)]

        await push(0, True)  # imu_enable is 0: ignored
        for _ in range(250):  # until a frame without samples went out
            await Timer(1, unit="us")
            if await frames_seen():
                break
        assert all(f.imu is None for f in await frames_seen())
        await command(dut, out, tactile.REG_IMU_ENABLE, 1)
        i = 1
        for _ in range(10):  # one sample every 35 us: about three per window
            await push(i, True)
            sent.append(i)
            i += 1
            await Timer(35, unit="us")
        for _ in range(11):  # a burst within one window: 11 samples, the frame keeps the last 8
            await push(i, False)
            sent.append(i)
            i += 1
        for _ in range(3):
            await Timer(35, unit="us")
            await push(i, True)
            sent.append(i)
            i += 1
        await Timer(250, unit="us")
        frames = await frames_seen()
        assert decoder.stats["crc_errors"] == 0 and decoder.stats["bytes_discarded"] == 0
        assert all(not f.status & tactile.STATUS_FRAME_DROPPED for f in frames)
        got = []  # (frame, sample indices)
        for f in frames:
            if f.imu is None:
                continue
            ints = np.rint(np.asarray(f.imu, np.float64) / tactile.IMU_SCALE).astype(int)
            idx = [int(np.flatnonzero((samples == row).all(axis=1))[0]) for row in ints]
            got.append((f, idx))
            # the frame's bytes are exactly what the Python encoder makes of it
            want = tactile.encode_frame(tactile.TactileFrame(f.sequence, f.timestamp_us, f.impedance,
                                                             samples[idx] * tactile.IMU_SCALE, f.tx_mask,
                                                             f.rx_mask, f.status))
            assert want in raw, f"frame {f.sequence}: bytes differ from encode_frame"
        assert got and sum(len(idx) for _, idx in got) >= 12, [idx for _, idx in got]
        expected = 0  # position in `sent` of the next sample
        for f, idx in got:
            first = sent.index(idx[0])
            assert idx == sent[first:first + len(idx)], idx
            if f.status & tactile.STATUS_IMU_OVERFLOW:
                assert len(idx) == 8 and first > expected
            else:
                assert first == expected, (first, expected)
            expected = first + len(idx)
        assert expected == len(sent), "every sample sent was carried"
        assert any(f.status & tactile.STATUS_IMU_OVERFLOW for f, _ in got)

    @cocotb.test()
    async def dropped_frames_keep_their_data(dut) -> None:
        """A window shorter than a frame on the link: every other frame is dropped (sequence gap,
        status bit 2 on the next one), and the frames that do go out hold one window each.
        Comparator bits: pattern A in even windows, B in odd ones, the same sequence in every window
        of a kind; every line makes whole cycles in the 128-tick window, so windows of a kind have
        equal sums. Reference sums of reception line 0 from short frames (rx_enable 1, nothing
        dropped), then all lines: a frame that mixed two windows would differ from the reference.
        Timestamps: 256 us per window, device time since reset."""
        decoder, out = await start(dut)
        t_reset = get_sim_time("ns")
        rng = np.random.default_rng(9)
        patterns = rng.integers(0, 1 << NRX, (2, 128))

        async def comparators() -> None:
            w, n = 0, 0  # window number, tick in the window
            while True:
                await RisingEdge(dut.clk)
                if int(dut.win_end.value):  # the next tick is the first of a window
                    w, n = w + 1, 0
                    await FallingEdge(dut.clk)
                    dut.adc_cmp.value = int(patterns[w % 2, 0])
                elif int(dut.strobe.value):  # tick n started: bits for tick n + 1
                    await FallingEdge(dut.clk)
                    dut.adc_cmp.value = int(patterns[w % 2, (n + 1) % 128])
                    n += 1

        async def collect(count: int) -> list:
            out.clear()
            for _ in range(800):
                await Timer(1, unit="us")
                frames = [o for o in out if isinstance(o, tactile.TactileFrame)]
                if len(frames) >= count:
                    return frames
            raise AssertionError(f"{len(frames)} frames, expected {count}")

        cocotb.start_soon(comparators())
        await command(dut, out, tactile.REG_TICK_DIV, 20)
        await command(dut, out, tactile.REG_WINDOW, 128)  # 25.6 us
        await command(dut, out, tactile.REG_RX_ENABLE, 0x1, timeout_us=60)  # 4 cells: 18 us on the link
        short = (await collect(7))[3:]
        assert all(not f.status for f in short), [f.status for f in short]
        ref = {f.sequence % 2: f.impedance[:NTX, 0] for f in short}
        assert len(ref) == 2 and not np.array_equal(ref[0], ref[1])
        for f in short:
            assert np.array_equal(f.impedance[:NTX, 0], ref[f.sequence % 2])
        await command(dut, out, tactile.REG_RX_ENABLE, 0xF, timeout_us=60)  # 16 cells: 37 us on the link
        full = (await collect(8))[2:]
        assert decoder.stats["crc_errors"] == 0
        for prev, f in zip(full[:-1], full[1:], strict=True):
            assert f.sequence > prev.sequence + 1 and f.status & tactile.STATUS_FRAME_DROPPED, (prev, f)
        for f in full:
            assert np.array_equal(f.impedance[:NTX, 0], ref[f.sequence % 2]), f"frame {f.sequence} mixes windows"
        for prev, f in zip(short[:-1] + full[:-1], short[1:] + full[1:], strict=True):  # 128 x 20 clocks = 256 us
            assert abs(f.timestamp_us - prev.timestamp_us - 256 * (f.sequence - prev.sequence)) <= 1, (prev, f)
        # device time since reset (a device microsecond is CLK_PER_US = 10 clocks of 10 ns here)
        elapsed = (get_sim_time("ns") - t_reset) / 100
        assert 0 < elapsed - full[-1].timestamp_us < 1000, (elapsed, full[-1].timestamp_us)
        assert np.abs(full[0].impedance[:NTX, :NRX]).min() > 0

    async def analog(dut, G: np.ndarray, C: np.ndarray) -> None:
        """Per sample tick: DAC bits -> 2-pole RC -> cell currents -> ADC integrators -> comparators."""
        alpha = 0.3
        y1 = np.zeros(NTX)
        y2 = np.zeros(NTX)
        prev = np.zeros(NTX)
        u = np.zeros(NRX)
        while True:
            await RisingEdge(dut.strobe)
            await ReadOnly()
            dac = int(dut.dac_out.value)
            fb = int(dut.adc_fb.value)
            x = np.array([2.0 * (dac >> k & 1) - 1 for k in range(NTX)])
            y1 += alpha * (x - y1)
            y2 += alpha * (y1 - y2)
            current = G.T @ y2 + C.T @ (y2 - prev)
            prev = y2.copy()
            u += current - np.array([2.0 * (fb >> j & 1) - 1 for j in range(NRX)])
            await FallingEdge(dut.clk)
            dut.adc_cmp.value = sum(int(u[j] > 0) << j for j in range(NRX))
