"""`xm eval` provenance: --merge keeps rows of the same experiment only; --seeds/--draws pools
runs into mean, spread and paired ratios; a method whose training fails is a row saying so."""

from __future__ import annotations

import json

import numpy as np
import pytest

from evaluation import evaluate as E
from evaluation import runs
from evaluation.evaluate import EvaluationError, evaluate
from evaluation.evaluate import main as eval_main
from services.policy.flat_state import BaselineError
from tests.unit.policy_demos import synthetic_protocol


@pytest.fixture(scope="module")
def demos():
    return synthetic_protocol(train=3, validation=2, steps=40)


def test_merge_refuses_another_seed_or_draw_or_budget(tmp_path, demos):
    evaluate(methods=["naive"], out_dir=tmp_path, quick=True, progress=False, demos=demos, seed=3)
    meta = json.loads((tmp_path / "run.json").read_text())
    assert meta["seed"] == 3 and set(meta["versions"]) == {"naive"}
    for kwargs, what in (({"seed": 4}, "seed"), ({"seed": 3, "draw": 1}, "draw"), ({"seed": 3, "quick": False},
                                                                                      "quick")):
        kw = {"quick": True, **kwargs}
        with pytest.raises(EvaluationError, match=f"--merge refused.*{what}"):
            evaluate(methods=["promp_simple"], out_dir=tmp_path, progress=False, demos=demos, merge=True, **kw)
    kept = evaluate(methods=["promp_simple"], out_dir=tmp_path, quick=True, progress=False, demos=demos, seed=3,
                    merge=True)
    assert list(kept) == ["promp_simple", "naive"]


def test_merge_refuses_rows_of_another_code_version(tmp_path, demos, monkeypatch):
    evaluate(methods=["naive"], out_dir=tmp_path, quick=True, progress=False, demos=demos)
    real = runs.code_version
    monkeypatch.setattr(runs, "code_version", lambda m, rec=False: "0" * 12 if m == "naive" else real(m, rec))
    with pytest.raises(EvaluationError, match="row naive from code version .* the code is now 000000000000"):
        evaluate(methods=["promp_simple"], out_dir=tmp_path, quick=True, progress=False, demos=demos, merge=True)
    (tmp_path / "run.json").unlink()  # results of unknown provenance are not merged either
    with pytest.raises(EvaluationError, match="no run.json"):
        evaluate(methods=["promp_simple"], out_dir=tmp_path, quick=True, progress=False, demos=demos, merge=True)


def test_code_version_follows_the_rows_sources_only():
    assert runs.code_version("promp_simple") == runs.code_version("promp_conditional")
    assert runs.code_version("naive") != runs.code_version("dmp")
    assert runs.code_version("multimodal") == runs.code_version("time_window")


def test_a_method_that_fails_to_train_is_a_row_saying_so(tmp_path, demos, monkeypatch):
    class Diverges:
        name = "dmp"

        def fit(self, train, progress=True):
            raise BaselineError("training loss became nan at iteration 3")

    real = E.make
    monkeypatch.setattr(E, "make", lambda name, quick=False, seed=0: Diverges() if name == "dmp" else real(name, quick,
                                                                                                           seed))
    res = evaluate(methods=["dmp", "naive"], out_dir=tmp_path, quick=True, progress=False, demos=demos)
    assert res["dmp"]["hand"] == float("inf") and np.isfinite(res["naive"]["hand"])
    assert "nan" in json.loads((tmp_path / "run.json").read_text())["failed"]["dmp"]


def _fake_run(folder, seed, draw, ours, base, version="v1"):
    folder.mkdir(parents=True)
    keys = ("hand", "object", "hand_masked", "object_masked")
    (folder / "results.json").write_text(json.dumps({"multimodal": dict.fromkeys(keys, ours),
                                                     "dmp": dict.fromkeys(keys, base)}))
    (folder / "run.json").write_text(json.dumps({"task": "assembly", "seed": seed, "draw": draw, "quick": False,
                                                 "observations": "truth", "changes": {}, "failed": {},
                                                 "versions": {"multimodal": version, "dmp": "d"}}))
    return folder


def test_summary_reports_mean_spread_and_paired_ratio(tmp_path):
    folders = [_fake_run(tmp_path / f"r{i}", i, 0, ours, base)
               for i, (ours, base) in enumerate([(0.02, 0.04), (0.03, 0.06), (0.025, 0.05)])]
    s = runs.summarize(folders)
    assert s["rows"]["multimodal"]["hand"]["mean"] == pytest.approx(0.025)
    assert s["rows"]["multimodal"]["hand"]["std"] == pytest.approx(0.005)
    ratio = s["best_baseline"]["hand"]
    assert ratio["row"] == "dmp" and ratio["mean"] == pytest.approx(2.0) and ratio["std"] == pytest.approx(0.0)
    assert not ratio["within_spread"]
    text = runs.summary_table(s, E.ROWS)
    assert "(5) DMP" in text and "2.00x" in text and "3 runs" in text


def test_summary_refuses_runs_of_different_code_versions(tmp_path):
    a = _fake_run(tmp_path / "a", 0, 0, 0.02, 0.04)
    b = _fake_run(tmp_path / "b", 1, 0, 0.02, 0.04, version="v2")
    with pytest.raises(runs.RunError, match="row multimodal comes from code versions"):
        runs.summarize([a, b])


@pytest.mark.slow
def test_xm_eval_seeds_and_draws_write_every_run_and_the_summary(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(E, "assembly_protocol", lambda seed: synthetic_protocol(train=3, validation=2, steps=20))
    assert eval_main(["--quick", "--seeds", "0,1", "--draws", "2", "--methods", "multimodal,naive", "--out",
                      str(tmp_path), "--no-progress"]) == 0
    assert sorted(p.name for p in tmp_path.glob("seed*")) == ["seed0-draw0", "seed0-draw1", "seed1-draw0",
                                                              "seed1-draw1"]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["rows"]["naive"]["n"] == 4 and summary["best_baseline"]["hand"]["n"] == 4
    assert "4 runs" in capsys.readouterr().out
    assert eval_main(["--seeds", "x", "--out", str(tmp_path)]) == 2
