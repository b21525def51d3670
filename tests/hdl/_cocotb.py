"""Runs cocotb test functions on Icarus from a pytest test; the marks every HDL test carries."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

HDL_MARKS = [pytest.mark.hdl, pytest.mark.skipif(shutil.which("iverilog") is None,
                                                 reason="iverilog not installed (apt-get install -y iverilog)")]


def run_cocotb(sources: list[Path], toplevel: str, test_module: str, build: Path, expect: int,
               parameters: dict | None = None, testcase: list[str] | None = None) -> None:
    """Builds ``sources`` around ``toplevel`` and runs the cocotb tests of ``test_module`` (this folder)
    in Icarus; fails unless exactly ``expect`` of them ran and all passed."""
    from cocotb_tools.runner import get_results, get_runner  # optional: only the HDL tests need cocotb

    runner = get_runner("icarus")
    runner.build(sources=sources, hdl_toplevel=toplevel, build_dir=build, always=True, parameters=parameters or {},
                 timescale=("1ns", "1ps"))
    env = {"PYTHONPATH": os.pathsep.join([str(ROOT), str(Path(__file__).parent)] + sys.path)}
    results = runner.test(hdl_toplevel=toplevel, test_module=test_module, testcase=testcase, build_dir=build,
                          test_dir=build, extra_env=env)
    total, failed = get_results(results)
    assert total == expect and failed == 0, f"{failed} of {total} cocotb tests failed (of {expect}); log in {build}"
