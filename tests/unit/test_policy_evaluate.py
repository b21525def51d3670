"""`xm eval` bookkeeping: a later run of some methods can keep the other rows of an earlier run;
saved rollouts are scored again without fitting."""

from __future__ import annotations

import json

import numpy as np
import pytest

from evaluation.evaluate import EvaluationError, evaluate, rescore, rollouts, score, split
from evaluation.evaluate import main as eval_main
from learning.cli import train_main
from learning.ours import Ours
from learning.presets import preset
from learning.train import fit_model
from services.policy.model import Policy
from services.world.teacher import assembly_protocol


@pytest.fixture(scope="module")
def demos():
    return assembly_protocol(0)


@pytest.mark.slow
def test_merge_keeps_earlier_rows_and_replaces_rerun_ones(tmp_path, demos):
    first = evaluate(methods=["naive", "promp_simple"], out_dir=tmp_path, quick=True, progress=False, demos=demos)
    again = evaluate(methods=["naive"], out_dir=tmp_path, quick=True, progress=False, demos=demos, merge=True)
    assert list(again) == ["promp_simple", "naive"]  # Table 7.1 order, whatever order they were run in
    assert again["promp_simple"] == first["promp_simple"]
    assert json.loads((tmp_path / "results.json").read_text()) == again
    assert "(7) Simple ProMP" in (tmp_path / "results.md").read_text()
    alone = evaluate(methods=["naive"], out_dir=tmp_path, quick=True, progress=False, demos=demos)
    assert list(alone) == ["naive"]


@pytest.mark.slow
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


@pytest.mark.slow
def test_xm_train_teacher_keeps_the_final_weights_unless_told(tmp_path):
    """`xm train --teacher S` keeps the validation layouts unseen (as row (1) of `xm eval`), so the
    robot loop on them is out of sample; --select validation picks on them instead."""
    assert train_main(["--teacher", "0", "--steps", "2", "--out", str(tmp_path / "a")]) == 0
    info = json.loads((tmp_path / "a" / "train.json").read_text())
    assert (info["selection_demos"], info["kept"], info["best_step"]) == (0, "final weights", 2)
    assert train_main(["--teacher", "0", "--steps", "2", "--select", "validation", "--out", str(tmp_path / "b")]) == 0
    assert json.loads((tmp_path / "b" / "train.json").read_text())["selection_demos"] == 12


@pytest.mark.slow
def test_selection_keeps_the_best_held_out_checkpoint_and_otherwise_the_last():
    """With held-out demos every scored checkpoint competes; without, only the final one is scored and kept."""
    train_d, val_d = split(assembly_protocol(0))
    cfg = preset("single_state", steps=6, eval_every=1, eval_from=0.0, hidden=(32, 32), batch=32)
    held = fit_model(Ours(cfg), train_d, val_d[:2], progress=False)
    assert [e["step"] for e in held.evals] == [1, 2, 3, 4, 5, 6]
    best = min(held.evals, key=lambda e: e["score"])
    assert (held.best_step, held.best_score) == (best["step"], best["score"])
    final = fit_model(Ours(cfg), train_d, None, progress=False)
    assert [e["step"] for e in final.evals] == [6] and final.best_step == 6


@pytest.mark.slow
def test_a_training_draw_changes_the_learned_rows_and_only_them(tmp_path, demos):
    """--draw K trains from other random numbers: another net for our rows, the same for draw 0
    run twice, and the deterministic baselines unchanged."""
    runs = {}
    for name, draw in (("a", 0), ("b", 0), ("c", 1)):
        runs[name] = evaluate(methods=["single_state", "promp_simple"], out_dir=tmp_path / name, quick=True,
                              progress=False, demos=demos, draw=draw)
    assert runs["a"] == runs["b"]
    assert runs["c"]["single_state"] != runs["a"]["single_state"]
    assert runs["c"]["promp_simple"] == runs["a"]["promp_simple"]
    assert "training draw 1" in (tmp_path / "c" / "results.md").read_text()
    assert "draw" not in (tmp_path / "a" / "results.md").read_text()


def test_xm_eval_and_train_refuse_an_unknown_config_change(tmp_path, capsys):
    assert eval_main(["--set", "reservoir_period=1,2", "--out", str(tmp_path)]) == 2
    assert "reservoir_period=1,2" in capsys.readouterr().err
    assert train_main(["--teacher", "0", "--set", "steps=many", "--out", str(tmp_path)]) == 2
    assert "not a int" in capsys.readouterr().err
    # where nothing is trained a change would be silently ignored: refused instead
    for mode in ("--execute", "--rescore"):
        assert eval_main([mode, "--set", "max_speed=1.2", "--out", str(tmp_path)]) == 2
        assert "--set changes the training" in capsys.readouterr().err
    assert eval_main(["--execute", "--catch-mm", "-5", "--out", str(tmp_path)]) == 2
    assert "--catch-mm must be 0 or a positive" in capsys.readouterr().err


@pytest.mark.slow
def test_xm_eval_keeps_the_net_it_scored(tmp_path, demos):
    """policy_<row>.pt is the very net of the row: reloaded, it scores the same; baselines leave none."""
    rows = evaluate(methods=["single_state", "time_window", "promp_simple"], out_dir=tmp_path, quick=True,
                    progress=False, demos=demos, changes={"max_speed": 1.2})
    assert "rows (1)-(4) with max_speed=1.2" in (tmp_path / "results.md").read_text()
    assert sorted(p.name for p in tmp_path.glob("policy_*.pt")) == ["policy_single_state.pt",
                                                                    "policy_time_window.pt"]
    val = split(demos)[1]
    for name in ("single_state", "time_window"):
        reloaded = Policy.load(str(tmp_path / f"policy_{name}.pt"))
        assert reloaded.inference.max_speed == 1.2
        assert score(rollouts(reloaded, val, False), val) == pytest.approx(rows[name], abs=1e-9)
    assert Policy.load(str(tmp_path / "policy_time_window.pt")).cfg.window == (8, 4, 2, 1, 1)
