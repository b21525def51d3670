"""`xm eval` bookkeeping: a later run of some methods can keep the other rows of an earlier run."""

from __future__ import annotations

import json

from services.policy.evaluate import evaluate
from services.world.teacher import assembly_protocol


def test_merge_keeps_earlier_rows_and_replaces_rerun_ones(tmp_path):
    demos = assembly_protocol(0)
    first = evaluate(methods=["naive", "promp_simple"], out_dir=tmp_path, quick=True, progress=False, demos=demos)
    again = evaluate(methods=["naive"], out_dir=tmp_path, quick=True, progress=False, demos=demos, merge=True)
    assert list(again) == ["promp_simple", "naive"]  # Table 7.1 order, whatever order they were run in
    assert again["promp_simple"] == first["promp_simple"]
    assert json.loads((tmp_path / "results.json").read_text()) == again
    assert "(7) Simple ProMP" in (tmp_path / "results.md").read_text()
    alone = evaluate(methods=["naive"], out_dir=tmp_path, quick=True, progress=False, demos=demos)
    assert list(alone) == ["naive"]
