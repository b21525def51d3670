"""`xm eval` bookkeeping: a later run of some methods can keep the other rows of an earlier run;
saved rollouts are scored again without fitting."""

from __future__ import annotations

import json

import numpy as np
import pytest

from services.policy.evaluate import EvaluationError, evaluate, rescore
from services.world.teacher import assembly_protocol


@pytest.fixture(scope="module")
def demos():
    return assembly_protocol(0)


def test_merge_keeps_earlier_rows_and_replaces_rerun_ones(tmp_path, demos):
    first = evaluate(methods=["naive", "promp_simple"], out_dir=tmp_path, quick=True, progress=False, demos=demos)
    again = evaluate(methods=["naive"], out_dir=tmp_path, quick=True, progress=False, demos=demos, merge=True)
    assert list(again) == ["promp_simple", "naive"]  # Table 7.1 order, whatever order they were run in
    assert again["promp_simple"] == first["promp_simple"]
    assert json.loads((tmp_path / "results.json").read_text()) == again
    assert "(7) Simple ProMP" in (tmp_path / "results.md").read_text()
    alone = evaluate(methods=["naive"], out_dir=tmp_path, quick=True, progress=False, demos=demos)
    assert list(alone) == ["naive"]


def test_rescore_reads_the_saved_rollouts_back(tmp_path, demos):
    first = evaluate(methods=["naive", "dmp"], out_dir=tmp_path, quick=True, progress=False, demos=demos)
    assert rescore(tmp_path, 0, demos) == first
    # a rollout changed on disk changes its score: the scores come from the files, not a cache
    with np.load(tmp_path / "rollouts_naive.npz") as z:
        arrays = dict(z)
    arrays["objects_0"] = arrays["objects_0"] + 0.05
    np.savez_compressed(tmp_path / "rollouts_naive.npz", **arrays)
    again = rescore(tmp_path, 0, demos)
    assert again["naive"]["object"] > first["naive"]["object"] and again["dmp"] == first["dmp"]
    with pytest.raises(EvaluationError, match="seed 0, not 1"):
        rescore(tmp_path, 1, demos)
    with pytest.raises(EvaluationError, match="no rollouts"):
        rescore(tmp_path / "empty", 0, demos)
    del arrays["hands_11"]  # a truncated file is named, not a KeyError
    np.savez_compressed(tmp_path / "rollouts_naive.npz", **arrays)
    with pytest.raises(EvaluationError, match="rollouts_naive.npz is unreadable or incomplete"):
        rescore(tmp_path, 0, demos)
    (tmp_path / "rollouts_naive.npz").write_bytes(b"not a zip")
    with pytest.raises(EvaluationError, match="rollouts_naive.npz is unreadable"):
        rescore(tmp_path, 0, demos)


def test_xm_train_teacher_selects_on_the_training_starts_unless_told(tmp_path):
    """`xm train --teacher S` keeps the validation layouts unseen (as row (1) of `xm eval`), so the
    robot loop on them is out of sample; --select validation picks on them instead."""
    from services.policy.train import main as train_main

    assert train_main(["--teacher", "0", "--steps", "2", "--out", str(tmp_path / "a")]) == 0
    assert json.loads((tmp_path / "a" / "train.json").read_text())["selection_demos"] == 3
    assert train_main(["--teacher", "0", "--steps", "2", "--select", "validation", "--out", str(tmp_path / "b")]) == 0
    assert json.loads((tmp_path / "b" / "train.json").read_text())["selection_demos"] == 12
