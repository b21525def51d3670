"""The whole simulated workcell (deploy/sim.toml through `xm up`): a 10 s recording of every
registered key, each key's rate in the deployment's time base (sim time, from the message stamps)
against its nominal rate. Baseline in the same run: how much sim time passed per wall second while
recording (the world's real-time factor), read off the recorded xm/clock, since on a loaded machine
every rate in wall time scales with it.
Writes .bench/workcell.json. Target: every key within +-20 % of nominal (on-change keys: at least
nominal - 20 %)."""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from mcap_ros2.reader import read_ros2_messages

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere

from shared import keys  # noqa: E402
from tests.conftest import sim_workcell  # noqa: E402
from tests.integration.test_workcell import record, stamp_of  # noqa: E402

SECONDS = 10.0


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    with tempfile.TemporaryDirectory() as tmp, sim_workcell(Path(tmp)) as cell:
        t0 = time.perf_counter()
        out = record(cell, SECONDS, "bench.mcap")
        wall = time.perf_counter() - t0
        stamps: dict[str, list[float]] = defaultdict(list)
        for m in read_ros2_messages(str(out)):
            stamps[m.channel.topic].append(stamp_of(m.ros_msg))
    clock = sorted(stamps["xm/clock"])
    rows, met = {}, True
    for spec in keys.REGISTRY:
        ts = sorted(stamps.get(spec.key, []))
        rate = (len(ts) - 1) / (ts[-1] - ts[0]) if len(ts) >= 2 and ts[-1] > ts[0] else 0.0
        ratio = rate / spec.rate_hz
        ok = 0.8 <= ratio and (spec.on_change or ratio <= 1.2)
        met &= ok
        rows[spec.key] = {"messages": len(ts), "rate_hz": rate, "nominal_hz": spec.rate_hz,
                          "ratio_to_nominal": ratio, "on_change": spec.on_change, "within_target": ok}
    res = {"recorded_wall_s": SECONDS, "record_command_wall_s": wall,
           "sim_seconds_per_wall_second": (clock[-1] - clock[0]) / SECONDS if len(clock) >= 2 else 0.0,
           "keys": rows, "all_within_target": met,
           "targets": {"ratio_to_nominal_min": 0.8, "ratio_to_nominal_max": 1.2}}
    Path(".bench").mkdir(exist_ok=True)
    Path(".bench/workcell.json").write_text(json.dumps(res, indent=2))
    print(f"real-time factor {res['sim_seconds_per_wall_second']:.2f} sim s per wall s")
    print(f"{'key':<32}{'msgs':>6}{'Hz':>8}{'nominal':>9}{'ratio':>7}")
    for key, r in rows.items():
        print(f"{key:<32}{r['messages']:>6}{r['rate_hz']:>8.1f}{r['nominal_hz']:>9.1f}{r['ratio_to_nominal']:>7.2f}"
              + ("" if r["within_target"] else "  outside +-20 %"))
    print("every key within +-20 % of nominal: " + ("met" if met else "NOT met"))


if __name__ == "__main__":
    main()
