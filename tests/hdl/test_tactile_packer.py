"""cocotb on Icarus: the FPGA frame packer produces exactly the bytes of the Python encoder
(shared/protocols/vectors/tactile.json). Skipped when iverilog is not installed."""

from __future__ import annotations

import json

from tests.hdl._cocotb import HDL_MARKS, ROOT, run_cocotb

HDL = ROOT / "hdl" / "tactile"
VECTORS = ROOT / "shared" / "protocols" / "vectors" / "tactile.json"


pytestmark = HDL_MARKS


def test_packer_bytes_match_the_vectors(tmp_path):
    run_cocotb([HDL / s for s in ("tb_packer.v", "tactile_packer.v", "tactile_framer.v", "crc32.v")], "tb_packer",
               "test_tactile_packer", tmp_path, expect=2)


# ---- cocotb side (runs inside the simulator; not collected by pytest: no test_ prefix) ----
try:
    import cocotb
    from cocotb.clock import Clock
    from cocotb.triggers import RisingEdge
except ImportError:  # pragma: no cover
    cocotb = None

if cocotb is not None:
    async def reset(dut) -> None:
        cocotb.start_soon(Clock(dut.clk, 10, unit="ns").start())
        dut.rst.value = 1
        dut.start.value = 0
        dut.wr_en.value = 0
        dut.out_ready.value = 0
        dut.imu_count.value = 0
        dut.imu_base.value = 0
        dut.imu_wr_en.value = 0
        for _ in range(3):
            await RisingEdge(dut.clk)
        dut.rst.value = 0

    async def load_matrix(dut, case: dict) -> None:
        for addr in range(256):
            re, im = case["real"][addr] & 0xFFFFFFFF, case["imag"][addr] & 0xFFFFFFFF
            dut.wr_addr.value = addr
            dut.wr_data.value = (im << 32) | re
            dut.wr_en.value = 1
            await RisingEdge(dut.clk)
        dut.wr_en.value = 0

    async def load_imu(dut, samples, base: int) -> None:
        """Raw samples (n x 6 int16) into the ring slots base, base + 1, ... (mod 16)."""
        for i, sample in enumerate(samples):
            for w, value in enumerate(sample):
                dut.imu_wr_addr.value = ((base + i) % 16) * 8 + w
                dut.imu_wr_data.value = int(value) & 0xFFFF
                dut.imu_wr_en.value = 1
                await RisingEdge(dut.clk)
        dut.imu_wr_en.value = 0
        dut.imu_count.value = len(samples)
        dut.imu_base.value = base

    async def send_frame(dut, case: dict, rng) -> bytes:
        """Start the packer on the loaded memory; collect the bytes with random back-pressure."""
        dut.seq.value = case["sequence"]
        dut.ts.value = case["timestamp_us"]
        dut.tx_mask.value = case["tx_mask"]
        dut.rx_mask.value = case["rx_mask"]
        dut.status.value = case["status"]
        dut.start.value = 1
        await RisingEdge(dut.clk)
        dut.start.value = 0
        got = bytearray()
        for _ in range(100_000):  # consumer with random back-pressure
            dut.out_ready.value = int(rng.random() < 0.7)
            await RisingEdge(dut.clk)
            if int(dut.out_valid.value) and int(dut.out_ready.value):
                got.append(int(dut.out_data.value))
                if int(dut.out_last.value):
                    break
            assert len(got) < 2000
        else:
            raise AssertionError(f"no last byte after 100000 clocks ({len(got)} bytes)")
        dut.out_ready.value = 0
        return bytes(got)

    @cocotb.test()
    async def packer_vectors(dut) -> None:
        import random

        await reset(dut)
        rng = random.Random(1)
        for case in json.loads(VECTORS.read_text()):
            if "real" not in case:
                continue
            await load_matrix(dut, case)
            got = await send_frame(dut, case, rng)
            want = bytes.fromhex(case["bytes"])
            if case["imu"] is not None:  # no IMU samples given here: compare against that encoding
                import numpy as np

                from shared.protocols import tactile

                z = (np.array(case["real"]) + 1j * np.array(case["imag"])).reshape(16, 16)
                want = tactile.encode_frame(tactile.TactileFrame(case["sequence"], case["timestamp_us"], z, None,
                                                                 case["tx_mask"], case["rx_mask"], case["status"]))
            assert bytes(got) == want, f"frame {case['sequence']}: got {bytes(got).hex()} want {want.hex()}"
            await RisingEdge(dut.clk)
            assert not int(dut.busy.value)

    @cocotb.test()
    async def packer_vectors_with_imu(dut) -> None:
        """IMU samples from the ring memory: the vectors file's IMU frame byte for byte, then every
        vector matrix with 0..8 random samples (full int16 range, slots wrapping past 15) against
        encode_frame."""
        import random

        import numpy as np

        from shared.protocols import tactile

        await reset(dut)
        rng = random.Random(2)
        nrng = np.random.default_rng(3)
        cases = [c for c in json.loads(VECTORS.read_text()) if "real" in c]
        with_imu = [c for c in cases if c["imu"] is not None]
        assert with_imu, "the vectors file has no frame with IMU samples"
        runs = []
        for case in with_imu:  # as the vectors file has it
            raw = np.clip(np.rint(np.asarray(case["imu"], np.float64) / tactile.IMU_SCALE), -32768, 32767)
            runs.append((case, raw.astype(int), 5, bytes.fromhex(case["bytes"])))
        for i, case in enumerate(cases):
            n = [8, 3, 0, 1][i % 4]
            raw = nrng.integers(-32768, 32768, (n, 6))
            raw[:, 0] = [-32768, 32767, 0, -1, 1, 12345, -2, 7][:n]
            z = (np.array(case["real"]) + 1j * np.array(case["imag"])).reshape(16, 16)
            want = tactile.encode_frame(tactile.TactileFrame(case["sequence"], case["timestamp_us"], z,
                                                             raw * tactile.IMU_SCALE, case["tx_mask"],
                                                             case["rx_mask"], case["status"] | 8))
            runs.append(({**case, "status": case["status"] | 8}, raw, 12 + i, want))
        for case, raw, base, want in runs:
            await load_matrix(dut, case)
            await load_imu(dut, raw, base)
            got = await send_frame(dut, case, rng)
            assert got == want, f"frame {case['sequence']}, {len(raw)} IMU: got {got.hex()} want {want.hex()}"
            decoded = tactile.StreamDecoder().feed(got)
            assert len(decoded) == 1 and len(decoded[0].imu if decoded[0].imu is not None else []) == len(raw)
            await RisingEdge(dut.clk)
            assert not int(dut.busy.value)
